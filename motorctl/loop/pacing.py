"""The loop's pacing: wake at absolute deadlines on a period grid of CLOCK_MONOTONIC.

Per period (as cyclictest and LinuxCNC's RTAPI pace a thread, with a busy-wait tail)::

    sleep to deadline − spin − early        (time.sleep: clock_nanosleep, absolute inside)
    [rehearse the next cycle]               only with enough time left (warm_caches)
    busy-wait to the deadline, read the clock: lateness = wake − deadline
    one or more whole periods late: the missed periods are counted and skipped, the deadline
    re-anchored on the grid (ros2_control's rule), never caught up in a burst

The rehearsal (``warm_caches``) runs the next cycle on copies so that the real one finds its
code and data in the CPU's caches (:func:`motorctl.loop.cycle.rehearse`). The pacer wakes
:data:`REHEARSAL_NS` earlier for it, or twice the last rehearsal when that is longer, and skips
it when less than :data:`REHEARSAL_MIN_NS` (or twice the last one) is left, so that a late wake
is not made later.
"""

from __future__ import annotations

import time

#: ``warm_caches``: the loop wakes this much earlier [ns] to rehearse the next cycle in its
#: spin tail (a rehearsal costs about one turnaround: 5-15 µs for two axes, 30 µs for 16; the
#: sleep overshoots by tens of µs), or twice the last rehearsal when that is longer
REHEARSAL_NS = 20_000
#: ... and rehearses only with at least this much left before the deadline [ns], and twice the
#: last rehearsal's time, so that a late wake is not made later
REHEARSAL_MIN_NS = 12_000


class Pacer:
    """Wakes its caller once per period at an absolute deadline (module docstring).

    Args:
        period_ns: the period [ns] (> 0).
        spin_ns: the busy-wait tail before each deadline [ns] (≥ 0).
        rehearse: optional callable() run in the tail before the deadline (the rehearsal of
            the next cycle), or None.
        clock: the clock [ns] (CLOCK_MONOTONIC: ``time.monotonic_ns``); sleep: sleeps [s]
            (``time.sleep``). Tests pass a clock they advance themselves.
    Attributes:
        deadline: the next deadline [ns] on ``clock``.
    Raises:
        ValueError: a period not positive or a negative spin.
    """

    def __init__(self, period_ns: int, spin_ns: int, rehearse=None, clock=time.monotonic_ns,
                 sleep=time.sleep):
        if period_ns <= 0 or spin_ns < 0:
            raise ValueError(f"period_ns must be > 0 and spin_ns >= 0, got {period_ns}, {spin_ns}")
        self.period_ns = int(period_ns)
        self.spin_ns = int(spin_ns)
        self.rehearse = rehearse
        self._clock = clock
        self._sleep = sleep
        self._early = self.spin_ns + (REHEARSAL_NS if rehearse is not None else 0)
        self._need = REHEARSAL_MIN_NS
        self._cap = self.period_ns // 4
        self.deadline = clock() + self.period_ns

    def restart(self) -> None:
        """The next deadline one period from now (after a deliberate pause: nothing missed)."""
        self.deadline = self._clock() + self.period_ns

    def wait(self) -> int:
        """Sleep, rehearse, spin to the deadline; return the lateness [ns] of the wake. When
        that is one or more whole periods (the caller counts ``late // period_ns`` missed),
        those periods are skipped; the deadline then moves to the next period."""
        clock, deadline, period = self._clock, self.deadline, self.period_ns
        rem = deadline - clock() - self._early
        if rem > 0:
            self._sleep(rem * 1e-9)
        if self.rehearse is not None:
            t_r = clock()
            if deadline - t_r >= self._need:
                self.rehearse()
                took = min(2 * (clock() - t_r), self._cap)   # a preempted one does not count in full
                self._need = took if took > REHEARSAL_MIN_NS else REHEARSAL_MIN_NS
                self._early = self.spin_ns + (took if took > REHEARSAL_NS else REHEARSAL_NS)
        while clock() < deadline:
            pass
        late = clock() - deadline
        if late >= period:
            deadline += (late // period) * period
        self.deadline = deadline + period
        return late
