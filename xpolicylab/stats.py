"""Latency statistics kept by the client, the checker and the bench."""

from __future__ import annotations

import numpy as np


class LatencyStats:
    """Round-trip times in milliseconds, with the percentiles an evaluation report needs."""

    def __init__(self) -> None:
        self.samples_ms: list[float] = []

    def record(self, ms: float) -> None:
        self.samples_ms.append(float(ms))

    def __len__(self) -> int:
        return len(self.samples_ms)

    def percentile(self, q: float) -> float:
        """The q-th percentile (0..100); NaN when nothing was recorded."""
        return float(np.percentile(self.samples_ms, q)) if self.samples_ms else float("nan")

    def summary(self) -> dict[str, float]:
        """``{count, mean_ms, p50_ms, p90_ms, p99_ms, max_ms}``."""
        if not self.samples_ms:
            return {"count": 0}
        return {
            "count": len(self.samples_ms),
            "mean_ms": float(np.mean(self.samples_ms)),
            "p50_ms": self.percentile(50),
            "p90_ms": self.percentile(90),
            "p99_ms": self.percentile(99),
            "max_ms": float(np.max(self.samples_ms)),
        }
