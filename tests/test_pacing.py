"""The loop's pacing (motorctl.loop.pacing.Pacer) on a clock the test advances itself: the
deadlines stay on the period grid, whole missed periods are skipped, never caught up, the
rehearsal runs only with time left and moves the wake earlier when it grows. No host timing."""

import pytest

from motorctl.loop.pacing import REHEARSAL_MIN_NS, REHEARSAL_NS, Pacer

PERIOD, SPIN = 200_000, 60_000


class FakeTime:
    """A clock [ns] that advances ``tick`` per read; sleep advances it by the time asked plus
    the overshoot the test sets for the next sleep."""

    def __init__(self, t0=1_000_000_000, tick=100):
        self.t, self.tick, self.overshoot, self.sleeps = t0, tick, 0, []

    def clock(self):
        self.t += self.tick
        return self.t

    def sleep(self, s):
        self.sleeps.append(s)
        self.t += int(round(s * 1e9)) + self.overshoot
        self.overshoot = 0


def test_wakes_stay_on_the_period_grid_with_only_the_clocks_own_lateness():
    ft = FakeTime()
    p = Pacer(PERIOD, SPIN, clock=ft.clock, sleep=ft.sleep)
    first = p.deadline
    lates = [p.wait() for _ in range(50)]
    assert max(lates) < 1_000                       # the spin's last clock reads
    assert p.deadline == first + 50 * PERIOD
    assert all(s * 1e9 <= PERIOD - SPIN for s in ft.sleeps)


def test_a_stall_is_skipped_on_the_grid_never_caught_up():
    ft = FakeTime()
    p = Pacer(PERIOD, SPIN, clock=ft.clock, sleep=ft.sleep)
    first = p.deadline
    p.wait()
    ft.overshoot = 3 * PERIOD + SPIN + 50_000       # the machine took the CPU for ~0.7 ms
    late = p.wait()
    assert late // PERIOD == 3
    assert (p.deadline - first) % PERIOD == 0
    assert p.deadline > ft.t and p.deadline - ft.t <= PERIOD
    assert p.wait() < 1_000                         # the next wake on time, not a burst of late ones


def test_restart_counts_a_deliberate_pause_as_nothing_missed():
    ft = FakeTime()
    p = Pacer(PERIOD, SPIN, clock=ft.clock, sleep=ft.sleep)
    p.wait()
    ft.t += 50 * PERIOD                             # e.g. a reconnection with every axis idle
    p.restart()
    assert p.wait() < 1_000


def test_the_rehearsal_runs_with_time_left_and_moves_the_wake_earlier_when_it_grows():
    ft = FakeTime()
    calls = []

    def rehearse(cost):
        calls.append(ft.t)
        ft.t += cost

    cost = {"ns": 5_000}
    p = Pacer(PERIOD, SPIN, lambda: rehearse(cost["ns"]), clock=ft.clock, sleep=ft.sleep)
    d = p.deadline
    p.wait()
    assert len(calls) == 1 and d - calls[0] >= SPIN + REHEARSAL_NS - 1_000   # woken early for it
    cost["ns"] = 20_000                             # a slow rehearsal (e.g. a cold cache) ...
    p.wait()
    d = p.deadline
    p.wait()                                        # ... makes the next wake twice that earlier
    assert d - calls[2] >= SPIN + 2 * 20_000 - 1_000
    assert p.wait() < 1_000                         # and the deadline is still met
    cost["ns"] = 150_000                            # one preempted inside: it counts a quarter period
    p.wait()
    d = p.deadline
    p.wait()
    assert SPIN + PERIOD // 4 - 1_000 <= d - calls[-1] <= SPIN + PERIOD // 4 + 1_000


def test_no_rehearsal_when_the_wake_comes_too_late_for_it():
    ft = FakeTime()
    calls = []
    p = Pacer(PERIOD, SPIN, lambda: calls.append(ft.t), clock=ft.clock, sleep=ft.sleep)
    ft.overshoot = SPIN + REHEARSAL_NS - REHEARSAL_MIN_NS // 2   # less than the minimum left
    assert p.wait() < PERIOD
    assert calls == []
    p.wait()
    assert len(calls) == 1


@pytest.mark.parametrize("period, spin", [(0, 0), (-5, 0), (PERIOD, -1)])
def test_a_bad_period_or_spin_is_refused(period, spin):
    with pytest.raises(ValueError, match="period_ns"):
        Pacer(period, spin)
