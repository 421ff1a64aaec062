"""The setpoint stream of commanded motion: a lock-free single-producer single-consumer ring
of (x_d, ẋ_d, ẍ_d) per axis per cycle in shared memory, and the loop's jerk-limited brake.

Who does what:
  * the producer (the daemon's I/O process, :mod:`motorctl.app.daemon.motion_side`) plans off
    the loop and writes rows ``w .. w+n-1`` at ``w % capacity``, then publishes ``w + n`` in
    ``ctl[SP_WRITE]`` (a release store after the rows' stores);
  * the consumer (the compiled cycle, :func:`stream_step`, once per cycle for every axis in
    the STREAM mode) reads ``ctl[SP_WRITE]`` (an acquire load), takes row ``r`` if
    ``r < w`` and publishes ``r + 1`` in ``ctl[SP_READ]``. No lock, no allocation, no wait.

A row is ``[epoch, x_0, v_0, a_0, x_1, v_1, a_1, ..., o_0, o_1, ...]`` ([m, m/s, m/s²] per
axis, then the value of every machine output of the ring, :attr:`SetpointRing.outputs`, as it
must be from that row's cycle on). The loop takes a row only when its epoch is
``ctl[SP_EPOCH]``: the consumer bumps the epoch at an underrun, so rows the producer planned
before it noticed are dropped, never followed from the wrong place.

**Outputs synchronised with motion** (LinuxCNC's motion-synchronised outputs, M62-M65, and here
every mapped machine word): the ring has one more row after its ``capacity``, the *applied* row,
whose output columns are the outputs the loop applies now. When the loop takes a row whose
outputs differ from the applied ones it copies them there and bumps ``ctl[SP_OUT_SEQ]``; the
loop then hands them to the driver before that very cycle's bus write and records them in that
cycle's run-log row (:func:`stream_outputs`): an output switches exactly at the row planned
for it. The outputs whose bit is set in ``ctl[SP_OUT_STOP]`` (a spindle, a torch, coolant) go
to 0 at once, in the same way, when the loop brakes on its own (an underrun or a stop) and
while no axis streams (a fault or a stop took them out of command mode).

An **underrun** (the ring empty while the last setpoint of a streaming axis still moves or
accelerates) is never a jump nor a fault: every streaming axis brakes along a jerk-limited
profile from its last (x, ẋ, ẍ) to rest (:func:`brake_step`, its own ``a_max`` and ``j_max``),
then holds there; ``ctl[SP_UNDERRUNS]`` counts the events and ``ctl[SP_BRAKING]`` says a
brake runs. The following-error check goes on as ever.
"""

from __future__ import annotations

import mmap

import numpy as np

from motorctl.jit import njit
from motorctl.ordering import load_acquire, store_release

#: the ring's control words (int64): rows written, rows read, the epoch rows must carry, the
#: underrun events, a brake running (1) or not (0), changes of the applied outputs, the outputs
#: switched off when the loop stops streaming (bit j: output j), the index of the first row not
#: taken at the last underrun (the one before it is the last setpoint followed: the producer
#: resumes the path there)
SP_WRITE, SP_READ, SP_EPOCH, SP_UNDERRUNS, SP_BRAKING, SP_OUT_SEQ, SP_OUT_STOP, SP_DRY = range(8)
SP_CTL = 8
#: the most outputs a ring carries (the bits of SP_OUT_STOP)
MAX_OUTPUTS = 32


class SetpointRing:
    """Shared-memory SPSC ring of per-cycle setpoints (module docstring); create it before
    ``fork``.

    Args:
        capacity: rows (cycles of setpoints), ≥ 1. n_axes: axes of the loop.
        shared: an anonymous shared mapping (True; the daemon) or plain process memory.
        outputs: the names of the machine outputs the rows carry (at most :data:`MAX_OUTPUTS`).
        stop_outputs: those of them switched off when the loop stops streaming (module docstring).
    Attributes:
        rows: (capacity + 1, 1 + 3·n_axes + n_outputs) float64 (the last row: the applied
        outputs); ctl: (SP_CTL,) int64; outputs: tuple of names.
    Raises:
        ValueError: too many outputs, a name twice, a stop output that is not an output.
    """

    def __init__(self, capacity: int, n_axes: int, shared: bool = True, outputs=(), stop_outputs=()):
        self.capacity, self.n_axes = int(capacity), int(n_axes)
        self.outputs = tuple(outputs)
        if len(self.outputs) > MAX_OUTPUTS or len(set(self.outputs)) != len(self.outputs):
            raise ValueError(f"a setpoint ring carries at most {MAX_OUTPUTS} distinct outputs "
                             f"(got {', '.join(self.outputs)})")
        if not set(stop_outputs) <= set(self.outputs):
            raise ValueError(f"stop outputs {sorted(set(stop_outputs) - set(self.outputs))} are not outputs "
                             f"of the ring ({', '.join(self.outputs)})")
        self.out0 = 1 + 3 * self.n_axes          # the first output column of a row
        self.width = self.out0 + len(self.outputs)
        nbytes = 8 * (SP_CTL + (self.capacity + 1) * self.width)
        if shared:
            self._mm = mmap.mmap(-1, nbytes, flags=mmap.MAP_SHARED)
            buf = np.frombuffer(self._mm, dtype=np.uint8)
        else:
            buf = np.zeros(nbytes, dtype=np.uint8)
        buf.fill(0)                       # every page made now: the loop never faults one in
        self.ctl = buf[:8 * SP_CTL].view(np.int64)
        self.rows = buf[8 * SP_CTL:].view(np.float64).reshape(self.capacity + 1, self.width)
        self.ctl[SP_OUT_STOP] = sum(1 << self.outputs.index(o) for o in set(stop_outputs))
        warm_up()

    # ---------------------------------------------------------------- producer side
    def depth(self) -> int:
        """Rows written and not yet read."""
        return int(self.ctl[SP_WRITE]) - int(load_acquire(self.ctl, SP_READ))

    def free(self) -> int:
        """Rows that can be written now."""
        return self.capacity - self.depth()

    def epoch(self) -> int:
        return int(self.ctl[SP_EPOCH])

    def push(self, block: np.ndarray, epoch: int, outs: np.ndarray | None = None) -> int:
        """Producer: write ``block`` ((n, n_axes, 3) float64: x, ẋ, ẍ per axis) tagged with
        ``epoch``, and ``outs`` ((n, n_outputs): every output's value from each row on; None:
        the applied outputs), as far as it fits. Returns the rows written."""
        n = min(block.shape[0], self.free())
        w = int(self.ctl[SP_WRITE])
        if outs is None:
            outs = np.repeat(self.applied()[None, :], n, axis=0)
        _put_rows(self.rows, w, np.ascontiguousarray(block[:n], dtype=np.float64).reshape(n, self.out0 - 1),
                  float(epoch), np.ascontiguousarray(outs[:n], dtype=np.float64))
        store_release(self.ctl, SP_WRITE, w + n)
        return n

    def applied(self) -> np.ndarray:
        """(n_outputs,) the outputs the loop applies now (a view of the applied row)."""
        return self.rows[self.capacity, self.out0:]

    def setpoint(self, row: int) -> np.ndarray:
        """(n_axes, 3) x, ẋ, ẍ per axis of ring row index ``row`` (a view)."""
        return self.rows[row % self.capacity, 1:self.out0].reshape(self.n_axes, 3)

    def row_outputs(self, row: int) -> np.ndarray:
        """(n_outputs,) the outputs of ring row index ``row`` (a view)."""
        return self.rows[row % self.capacity, self.out0:]

    def written(self) -> int:
        """Rows written since the ring was made (the index of the next row)."""
        return int(self.ctl[SP_WRITE])

    def consumed(self) -> int:
        """Rows the loop has taken (or dropped) since the ring was made."""
        return int(load_acquire(self.ctl, SP_READ))

    def replace(self, cut: int, block: np.ndarray, epoch: int, outs: np.ndarray) -> int | None:
        """Producer: the rows from index ``cut`` on replaced by ``block`` ((n, n_axes, 3)
        float64) tagged with ``epoch``, with ``outs`` ((n, n_outputs)), in one compiled step
        (a feed hold or an override acts on the setpoints the loop has not taken yet): the write
        index lowered to ``cut`` (a release store), the read index checked (the loop takes one
        row a cycle and only below the write index it loaded, so a row at least two past the
        read index seen after the store is never being read), the new rows written and ``cut +
        n`` published. No interpreter runs between the lowering and the publication, so the
        loop never finds the ring empty there (a retract and a later push left it two rows, 0.4
        ms, while the push took as long again: an underrun beside CPU hogs). Returns the rows
        written, or None (nothing changed) when ``cut`` is not below the write index or the
        loop is within two rows of it."""
        n = _replace_rows(self.ctl, self.rows, int(cut), block.reshape(block.shape[0], self.out0 - 1),
                          float(epoch), outs)
        return None if n < 0 else int(n)

    def underruns(self) -> int:
        return int(self.ctl[SP_UNDERRUNS])

    def braking(self) -> bool:
        return bool(self.ctl[SP_BRAKING])

    def dry_row(self) -> int:
        """The index of the last row the loop followed before its last underrun (-1: none)."""
        return int(self.ctl[SP_DRY]) - 1

    # ---------------------------------------------------------------- consumer side
    def drain(self, brake: bool) -> int:
        """Consumer, between cycles (the loop's own thread): every row not yet taken dropped
        (the read index set to the write index), the epoch bumped (rows the producer is still
        writing for the old one are dropped as they come, and the producer sees that the loop
        stopped following it), the stop outputs off, and with ``brake`` the brake of the axes
        still streaming started (they come to rest jerk-limited and hold; not counted as an
        underrun). What a fault, an axis's stop or a start in command mode calls for: no stale
        setpoint is ever followed. Returns the rows dropped. Nothing allocates."""
        return int(_drain(self.rows, self.ctl, brake, self.out0))


@njit
def _drain(sp, spc, brake, o0):
    """:meth:`SetpointRing.drain` compiled (``o0``: the first output column): the rows dropped."""
    w = load_acquire(spc, SP_WRITE)
    dropped = w - spc[SP_READ]
    spc[SP_EPOCH] += 1
    store_release(spc, SP_READ, w)
    spc[SP_BRAKING] = 1 if brake else 0
    _outputs_off(sp, spc, sp.shape[0] - 1, o0)
    return dropped


@njit
def _replace_rows(ctl, rows, cut, block, epoch, outs):
    """:meth:`SetpointRing.replace` compiled: the rows written (-1: none, nothing changed)."""
    cap = rows.shape[0] - 1
    w = ctl[SP_WRITE]
    if cut >= w or load_acquire(ctl, SP_READ) + 2 > cut:
        return -1
    store_release(ctl, SP_WRITE, cut)
    r = load_acquire(ctl, SP_READ)
    if r + 2 > cut:                            # the loop raced us: the rows as they were
        store_release(ctl, SP_WRITE, w)
        return -1
    n = min(block.shape[0], cap - (cut - r))
    _put_rows(rows, cut, block[:n], epoch, outs[:n])
    store_release(ctl, SP_WRITE, cut + n)
    return n


@njit
def _put_rows(rows, w, block, epoch, outs):
    """The rows of ring indices w, w+1, ... (at their index modulo the capacity) set to ``epoch``,
    ``block``'s (k, 3·n_axes) setpoints and ``outs``' (k, n_outputs) outputs; nothing published."""
    cap = rows.shape[0] - 1
    o0 = 1 + block.shape[1]
    for q in range(block.shape[0]):
        row = rows[(w + q) % cap]
        row[0] = epoch
        for c in range(block.shape[1]):
            row[1 + c] = block[q, c]
        for c in range(outs.shape[1]):
            row[o0 + c] = outs[q, c]


def warm_up() -> None:
    """Compile (or load the cached code of) the producer's compiled steps now (every ring does at
    its making: the daemon's before the fork), so that the first push, feed hold or override does
    not pay for it while the loop runs on the lead."""
    ctl = np.zeros(SP_CTL, dtype=np.int64)
    ctl[SP_WRITE] = 4
    _replace_rows(ctl, np.zeros((9, 4)), 3, np.zeros((2, 3)), 0.0, np.zeros((2, 0)))
    _put_rows(np.zeros((9, 4)), 0, np.zeros((2, 3)), 0.0, np.zeros((2, 0)))
    _drain(np.zeros((9, 4)), ctl, False, 4)


@njit
def _released(v, a, dj, ts):
    """The velocity left after ẍ is released to 0 at one jerk step dj per cycle from (ẋ, ẍ)."""
    while abs(a) > dj:
        a -= dj if a > 0.0 else -dj
        v += a * ts
    return v


@njit
def brake_step(x, v, a, a_max, j_max, ts):
    """One cycle of a jerk-limited stop from (x [m], ẋ [m/s], ẍ [m/s²]) with ``a_max``
    [m/s²] and ``j_max`` [m/s³] over ``ts`` [s]: the time-optimal bang-bang rule on the
    sampled profile: the jerk is ±j_max toward −sign(ẋ)·a_max as long as a release of ẍ to 0
    one cycle later would still not reverse ẋ, else toward ẍ = 0. Returns (x, ẋ, ẍ, at_rest);
    at rest ẋ = ẍ = 0 exactly (the last step changes ẍ by at most j_max·ts)."""
    dj = j_max * ts
    if abs(v) <= dj * ts and abs(a) <= dj:
        return x + 0.5 * v * ts, 0.0, 0.0, True
    sv = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else (-1.0 if a > 0.0 else 1.0))
    target = -sv * a_max
    a1 = max(a - dj, target) if a > target else min(a + dj, target)
    if _released(v + a1 * ts, a1, dj, ts) * sv < 0.0:
        target = 0.0                      # release now: ẋ reaches 0 with ẍ
    if a < target:
        a = min(a + dj, target)
    elif a > target:
        a = max(a - dj, target)
    v_new = v + a * ts
    if v_new * sv < 0.0 and abs(a) <= dj:   # the last step: never reverse
        v_new, a = 0.0, 0.0
    x += 0.5 * (v + v_new) * ts
    return x, v_new, a, False


@njit
def _outputs_off(sp, spc, cap, o0):
    """The stop outputs (bits of ``spc[SP_OUT_STOP]``) of the applied row ``sp[cap]`` to 0."""
    mask = spc[SP_OUT_STOP]
    changed = False
    for j in range(sp.shape[1] - o0):
        if (mask >> j) & 1 and sp[cap, o0 + j] != 0.0:
            sp[cap, o0 + j] = 0.0
            changed = True
    if changed:
        spc[SP_OUT_SEQ] += 1


@njit
def stream_outputs(sp, n_axes, row, base):
    """The applied outputs (the ring ``sp``'s last row, after its 1 + 3·n_axes setpoint columns)
    into the record row ``row`` from column ``base``: every cycle, whatever the axes do."""
    o0 = 1 + 3 * n_axes
    cap = sp.shape[0] - 1
    for j in range(sp.shape[1] - o0):
        row[base + j] = sp[cap, o0 + j]


@njit
def stream_step(sp, spc, ax, axf, c_mode, stream_mode, c_stop, c_x, c_amax, ts):
    """The stream's part of one cycle (module docstring) for the axes whose mode
    ``ax[i, c_mode]`` is ``stream_mode``: take one row of the ring ``sp``/``spc`` into their
    setpoint ``axf[i, c_x:c_x+3]`` (x [m], ẋ [m/s], ẍ [m/s²]); or, when the ring is empty while
    an axis still moves, or a stop is asked (``ax[i, c_stop]``) while it moves, brake
    (:func:`brake_step`) with ``axf[i, c_amax]`` and ``axf[i, c_amax + 1]`` (a_max, j_max).
    The outputs of a row taken become the applied ones; the stop outputs go off when a brake
    starts or no axis streams (module docstring). Returns True while a brake runs. Nothing
    allocates."""
    n = ax.shape[0]
    cap = sp.shape[0] - 1                        # the last row: the applied outputs
    o0 = 1 + 3 * n
    any_s = False
    for i in range(n):
        if ax[i, c_mode] == stream_mode:
            any_s = True
    if not any_s:
        _outputs_off(sp, spc, cap, o0)
        return False
    braking = spc[SP_BRAKING] != 0
    w = load_acquire(spc, SP_WRITE)
    r = spc[SP_READ]
    epoch = spc[SP_EPOCH]
    while r < w and sp[r % cap, 0] != epoch:     # rows of an older epoch: dropped
        r += 1
    got = False
    if braking:
        r = w                                    # a brake runs: nothing is followed
    elif r < w:
        row = sp[r % cap]
        for i in range(n):
            if ax[i, c_mode] == stream_mode:
                axf[i, c_x] = row[1 + 3 * i]
                axf[i, c_x + 1] = row[2 + 3 * i]
                axf[i, c_x + 2] = row[3 + 3 * i]
        changed = False
        for j in range(o0, sp.shape[1]):
            if sp[cap, j] != row[j]:
                sp[cap, j] = row[j]
                changed = True
        if changed:
            spc[SP_OUT_SEQ] += 1
        r += 1
        got = True
    store_release(spc, SP_READ, r)
    if not braking:
        moving = False
        stop = False
        for i in range(n):
            if ax[i, c_mode] == stream_mode and (axf[i, c_x + 1] != 0.0 or axf[i, c_x + 2] != 0.0):
                moving = True
                if ax[i, c_stop] != 0:
                    stop = True
        if moving and (stop or not got):
            braking = True
            spc[SP_EPOCH] = epoch + 1
            if not got:                          # an underrun: counted, where it ran dry
                spc[SP_DRY] = r
                spc[SP_UNDERRUNS] += 1
            _outputs_off(sp, spc, cap, o0)
    if braking:
        rest = True
        for i in range(n):
            if ax[i, c_mode] == stream_mode:
                x, v, a, done = brake_step(axf[i, c_x], axf[i, c_x + 1], axf[i, c_x + 2],
                                           axf[i, c_amax], axf[i, c_amax + 1], ts)
                axf[i, c_x] = x
                axf[i, c_x + 1] = v
                axf[i, c_x + 2] = a
                rest = rest and done
        if rest:
            braking = False
    spc[SP_BRAKING] = 1 if braking else 0
    return braking
