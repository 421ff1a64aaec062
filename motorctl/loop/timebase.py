"""The loop's time base: the one place where seconds become cycles and cycles become seconds."""

from __future__ import annotations

import math


class Timebase:
    """Period of the servo loop and the conversions every module uses.

    Args:
        period_s: loop period Ts [s] (> 0, finite).
    Attributes:
        period_s [s], period_ns [ns] (integer, for CLOCK_MONOTONIC deadlines), rate_hz [Hz].
    Raises:
        ValueError: period not positive and finite.
    """

    def __init__(self, period_s: float):
        period_s = float(period_s)
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"loop period must be positive and finite, got {period_s!r}")
        self.period_s = period_s
        self.period_ns = int(round(period_s * 1e9))
        self.rate_hz = 1.0 / period_s

    def cycles(self, seconds: float, minimum: int = 0) -> int:
        """Whole cycles nearest to ``seconds`` [s], at least ``minimum``."""
        return max(int(round(float(seconds) / self.period_s)), int(minimum))

    def cycles_ceil(self, seconds: float, minimum: int = 0) -> int:
        """Cycles needed to cover ``seconds`` [s] (rounded up), at least ``minimum``."""
        return max(int(math.ceil(float(seconds) / self.period_s - 1e-9)), int(minimum))

    def seconds(self, cycles: int) -> float:
        """Duration of ``cycles`` periods [s]."""
        return cycles * self.period_s
