"""Live progress of a run: episodes done/total, ETA, interactions per second, running success per dimension.

The runtime loop owns one `Progress` and calls `episode_finished(row)` when an episode is recorded,
`interactions(n)` after each batched policy call (n = environments served), and `close()` at the end.
Three modes, because people and scripts want different things:

* `rich`  - a live bar and a per-dimension line on stderr, for a person at a terminal;
* `jsonl` - one JSON object per finished episode, a `progress` line at most every `HEARTBEAT_S` while
  environments step (batched environments often finish their episodes together, minutes apart), and a final
  summary, for scripts and CI logs;
* `quiet` - nothing at all (the caller prints the final scores).

The ETA is extrapolated from the episodes finished in *this* process only: after a resume, the episodes
recorded before the crash count towards done/total and the running success rates, but not towards the speed.
Two speeds: `interactions_per_s` since the run started (compilation and start-up included) and
`recent_interactions_per_s` over the last `RATE_WINDOW_S` (what the run does now; the live bar shows it).
"""

from __future__ import annotations

import json
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import IO, Any

from rich.console import Console, Group
from rich.live import Live
from rich.progress import BarColumn, MofNCompleteColumn, Progress as RichProgress, TextColumn
from rich.text import Text

from dojo.compiler.taxonomy import builtin_taxonomy
from dojo.evaluation.episode import EpisodeResult

MODES = ("rich", "jsonl", "quiet")
RATE_WINDOW_S = 30.0
"""The recent speed counts the interactions of the last this many seconds."""
HEARTBEAT_S = 10.0
"""In `jsonl` mode, a `progress` line at most this often while environments step."""
REFRESH_S = 0.1
"""In `rich` mode, the display's numbers are brought up to date at most this often."""
FLUSH_S = 0.2
"""In `jsonl` mode, episode lines are flushed at most this long after they are written (and at every step and the
end): a batch of 2,048 environments ends its episodes together, and a flush per line was half of writing them."""


class Progress:
    """Progress of one run. `finished` are the episodes a resumed run found already recorded."""

    def __init__(
        self,
        total: int,
        *,
        mode: str = "rich",
        finished: Iterable[EpisodeResult] = (),
        stream: IO[str] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"progress mode must be one of {MODES}, got {mode!r}")
        if total < 0:
            raise ValueError("total must be >= 0")
        self.total = total
        self.mode = mode
        self._clock = clock
        self._start = clock()
        self._new_episodes = 0
        self._interactions = 0
        self._samples: deque[tuple[float, int]] = deque()  # (time, interactions so far) within RATE_WINDOW_S
        self._last_line = self._start
        self._last_flush = self._start
        self._last_refresh = -float("inf")
        self._unflushed = False
        self._closed = False
        self._dim_counts: dict[str, list[int]] = {}  # dimension -> [successes, episodes]
        self.done = 0
        for row in finished:
            self._count(row)
        self._resumed = self.done
        self._stream = stream if stream is not None else (sys.stdout if mode == "jsonl" else sys.stderr)
        self._live: Live | None = None
        if mode == "rich":
            self._bar = RichProgress(
                TextColumn("[bold]episodes"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[rate]}"), console=Console(file=self._stream),
            )
            self._bar_task = self._bar.add_task("run", total=total, completed=self.done, rate="")
            self._live = Live(self._renderable(), console=self._bar.console, refresh_per_second=4, transient=False)
            self._live.start()

    # -- called by the runtime loop -----------------------------------------------------------------------

    def episode_finished(self, row: EpisodeResult) -> None:
        self._count(row)
        self._new_episodes += 1
        if self.mode == "jsonl":
            self._last_line = self._clock()
            self._emit(flush=False, record={"event": "episode", **self.snapshot(), "episode": {
                "task": row.task, "dimension": row.dimension, "setting": row.setting, "split": row.split,
                "eval_seed": row.eval_seed, "index": row.episode, "success": row.success, "score": row.score,
                "steps": row.steps, "failure_reason": row.failure_reason,
            }})
        else:
            self._refresh()

    def interactions(self, n: int) -> None:
        """Count n environment-steps served by the policy (the runtime calls this per batched request)."""
        if n < 0:
            raise ValueError("interactions must be counted with n >= 0")
        self._interactions += n
        now = self._clock()
        self._samples.append((now, self._interactions))
        while self._samples[0][0] < now - RATE_WINDOW_S:
            self._samples.popleft()
        if self.mode == "jsonl" and now - self._last_line >= HEARTBEAT_S:
            self._last_line = now
            self._emit({"event": "progress", **self.snapshot()})
        elif self._unflushed:
            self._flush()
        self._refresh()

    def close(self) -> None:
        """Stop the live display and, in JSON-lines mode, write the summary line. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self._live is not None:
            self._refresh(force=True)
            self._live.stop()
            if not self._bar.console.is_terminal:  # rich ends the last frame with a newline on a terminal only:
                self._bar.console.line()          # in a log file the next line ran on after the display's
        if self.mode == "jsonl":
            self._emit({"event": "summary", **self.snapshot()})

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- state ---------------------------------------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """Everything the display shows, as plain data."""
        elapsed = max(self._clock() - self._start, 0.0)
        remaining = max(self.total - self.done, 0)
        eta = None
        if remaining == 0:
            eta = 0.0
        elif self._new_episodes and elapsed > 0:
            eta = remaining * elapsed / self._new_episodes
        return {
            "done": self.done,
            "total": self.total,
            "resumed": self._resumed,
            "elapsed_s": round(elapsed, 3),
            "eta_s": None if eta is None else round(eta, 1),
            "interactions": self._interactions,
            "interactions_per_s": round(self._interactions / elapsed, 2) if elapsed > 0 and self._interactions
            else None,  # a resumed run with nothing left to step has no rate (not a rate of 0)
            "recent_interactions_per_s": self._recent_rate(),
            "success_by_dimension": {
                d: {"successes": s, "episodes": n, "success_pct": round(100.0 * s / n, 2)}
                for d, (s, n) in ((d, self._dim_counts[d]) for d in _in_taxonomy_order(self._dim_counts))
            },
        }

    def _recent_rate(self) -> float | None:
        """Interactions per second since the oldest step counted in the window, up to now (a stalled run's rate
        falls); None before two steps were counted in it."""
        now = self._clock()
        recent = self._samples
        while recent and recent[0][0] < now - RATE_WINDOW_S:  # time only moves on: older samples are never read again
            recent.popleft()
        if len(recent) < 2 or now <= recent[0][0]:
            return None
        return round((recent[-1][1] - recent[0][1]) / (now - recent[0][0]), 2)

    def _count(self, row: EpisodeResult) -> None:
        self.done += 1
        counts = self._dim_counts.setdefault(row.dimension, [0, 0])
        counts[0] += int(row.success)
        counts[1] += 1

    # -- output --------------------------------------------------------------------------------------------

    def _emit(self, record: dict[str, Any], flush: bool = True) -> None:
        """Write one line; flushed now, or with `flush=False` once `FLUSH_S` has passed since the last flush."""
        self._stream.write(json.dumps(record) + "\n")
        self._unflushed = True
        if flush or self._clock() - self._last_flush >= FLUSH_S:
            self._flush()

    def _flush(self) -> None:
        self._stream.flush()
        self._last_flush, self._unflushed = self._clock(), False

    def _renderable(self) -> Group:
        snap = self.snapshot()
        dims = Text("  ".join(
            f"{builtin_taxonomy().label(d)} {v['success_pct']:.1f}% ({v['successes']}/{v['episodes']})"
            for d, v in snap["success_by_dimension"].items()
        ) or "no episodes finished yet", style="dim")
        return Group(self._bar, dims)

    def _refresh(self, force: bool = False) -> None:
        """Update the live display; at most every `REFRESH_S` unless `force` (it redraws only 4 times a second, and a
        batch ends thousands of episodes at once)."""
        if self._live is None or (not force and self._clock() - self._last_refresh < REFRESH_S):
            return
        self._last_refresh = self._clock()
        snap = self.snapshot()
        if not self._interactions and self._resumed:  # nothing stepped yet (or nothing left): no rate to show
            left = self.total - self.done
            rate = f"resumed: {self._resumed} already recorded" + (f", {left} to run" if left else ", nothing to run")
        else:
            eta = "ETA --" if snap["eta_s"] is None else f"ETA {_duration(snap['eta_s'])}"
            speed = snap["recent_interactions_per_s"] or snap["interactions_per_s"]
            ips = "--" if not speed else f"{speed:.1f}"
            rate = f"{eta}  {ips} interactions/s"
        self._bar.update(self._bar_task, completed=self.done, rate=rate)
        self._live.update(self._renderable())


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


def _in_taxonomy_order(dimensions: Iterable[str]) -> list[str]:
    """RoboDojo's dimensions in report order (scored, then training-only), then any a pack added."""
    known = builtin_taxonomy().ids
    return sorted(dimensions, key=lambda d: (known.index(d) if d in known else len(known), d))
