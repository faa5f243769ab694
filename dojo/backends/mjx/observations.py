"""A batched step's observations, each built the first time it is read.

An observation is a handful of small dicts per slot (`base.envelope`). Built for every slot of every tick, they
cost the host about 7 ms a tick at 2,048 slots on the CI machine, and about as much again to free a tick later,
while the GPU waits. The run loop reads only the observations of the slots the policy will be asked for next
(those whose action chunk runs out) unless it records every step: under a chunk of 8, one tick in 8. So the
backend hands out a sequence that keeps each bucket's state as the arrays it came in and makes a slot's
observation when it is read. What is read is the same dict, built from the same numbers, as when it was built
eagerly; images and privileged state are attached at the step (`add`), because the buffers they come from are
reused.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any, cast, overload

import numpy as np

from dojo.backends.base import Observation, envelope


class StepObservations(Sequence[Observation]):
    """Observations of one step's slots, in its order: position `at` is slot `ids[at]`, of `plans[at]`, at control
    step `steps[at]`, its robot state in row `rows[at]` of `states[buckets[at]]` (per bucket, one array per state
    name, owned by this object)."""

    def __init__(self, plans: list[Any], steps: list[int], buckets: list[int], rows: list[int],
                 states: Mapping[int, Mapping[str, np.ndarray]]) -> None:
        self._plans, self._steps, self._buckets, self._rows, self._states = plans, steps, buckets, rows, states
        self._added: dict[int, dict[str, Any]] = {}
        self._built: list[Observation | None] = [None] * len(plans)

    def add(self, at: int, fields: Mapping[str, Any]) -> None:
        """Fields observation `at` carries besides its state (images, privileged state), made at the step."""
        self._added.setdefault(at, {}).update(fields)
        built = self._built[at]
        if built is not None:
            built.update(fields)

    def __len__(self) -> int:
        return len(self._plans)

    @overload
    def __getitem__(self, at: int) -> Observation: ...

    @overload
    def __getitem__(self, at: slice) -> list[Observation]: ...

    def __getitem__(self, at: int | slice) -> Observation | list[Observation]:
        if isinstance(at, slice):
            return [self[k] for k in range(len(self))[at]]
        built = self._built[at]  # out of range: IndexError, as a list says it
        if built is None:
            at = at % len(self._built)
            row, state = self._rows[at], self._states[self._buckets[at]]
            built = self._built[at] = self._make(at, {name: column[row] for name, column in state.items()})
        return built

    def __iter__(self) -> Iterator[Observation]:
        """All of them, those not yet read built per bucket in one pass (a reset hands every one to the policy)."""
        missing = np.flatnonzero(np.fromiter((b is None for b in self._built), bool, len(self._built)))
        if missing.size:
            buckets, rows = np.asarray(self._buckets)[missing], np.asarray(self._rows)[missing]
            for k in np.unique(buckets).tolist():
                picked, state = buckets == k, self._states[k]
                columns = [list(column[rows[picked]]) for column in state.values()]
                for at, values in zip(missing[picked].tolist(), zip(*columns)):
                    self._built[at] = self._make(at, dict(zip(state, values)))
        return iter(cast(list[Observation], self._built))

    def _make(self, at: int, state: dict[str, np.ndarray]) -> Observation:
        """Observation `at` from its robot state: the envelope every backend returns, and what `add` attached."""
        built = envelope(self._plans[at], self._steps[at], state)
        built.update(self._added.get(at, ()))
        return built
