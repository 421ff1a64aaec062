"""The compiled paths compute what the Python paths compute, to the bit.

* The cycle: a law run by the compiled cycle (C2, PID+FF, C2 with a compensation of many
  families, adapted ones, a force ripple and an input delay among them) and the same law run
  from Python between the cycle's two calls (its ``law_code`` forced to LAW_PY; the
  compensation's terms evaluated from Python too) give the same record, row for row, through
  an approach, the program, a stop, and a fault.
* The simulated driver: its compiled read/write of every axis (the default plant: structural
  mode, current loop and its delay line, force and encoder noise, stiction) and each plant's
  Python step with one draw at a time from the same Generator give the same positions.
"""

from __future__ import annotations

import numpy as np
import pytest

from motorctl.app.build import build, shutdown, start
from motorctl.config import config_from_dict, load_config, load_yaml
from motorctl.ident.synth import EXAMPLES
from motorctl.control.base import LAW_PY
from motorctl.loop.cycle import A_LAW
from motorctl.loop.records import RecordLayout
from motorctl.loop.trajectory import Move

CYCLES = 6000


#: C2's compensation for the "c2-compensated" case: fixed and adapted terms of several families,
#: a thrust factor and a preview
COMPENSATION = {
    "cogging": {"period_m": 0.032, "sin_V": [0.05, 0.01], "cos_V": [0.02, -0.01], "adapt": True},
    "stribeck": {"force_V": 0.05, "velocity_m_per_s": 0.01},
    "spring": {"stiffness_V_per_m": 0.5, "rest_position_m": 0.2},
    "asymmetric_friction": {"coulomb_V": 0.02, "viscous_V_s_per_m": 0.01, "adapt": True},
    "periodic_disturbance": {"frequency_Hz": 7.3, "sin_V": [0.03], "cos_V": [0.01]},
    "position_friction_shape": {"bumps": [{"center_m": 0.2, "width_m": 0.05, "amplitude_V": 0.02}],
                                "offset_V": 0.001},
    "force_ripple": {"period_m": 0.05, "sin": [0.01], "cos": [0.005]},
    "input_delay": {"delay_s": 0.0004},
}


def _record(repo, law: str, python_law: bool) -> np.ndarray:
    d = load_yaml(repo / "configs" / "gantry.yaml")
    if law == "c2-compensated":
        law = "c2"
        d["axes"]["X"]["controller"]["compensation"] = COMPENSATION
    loaded = config_from_dict(d, "<gantry.yaml, compensated>")
    asm = build(loaded, ["X"], law, clock="virtual", capacity=CYCLES, operated=True)
    ctrl = asm.loop.controllers[0]
    if python_law:                                     # the same law, as one without a compiled step
        if getattr(ctrl, "compensation", None) is not None:
            ctrl.compensation.table = None             # its terms from Python
            ctrl._compiled_comp = False
            ctrl._bind()
        ctrl.detach()
        ctrl.__class__ = type(f"Py{type(ctrl).__name__}", (type(ctrl),), {"law_code": property(lambda self: LAW_PY)})
        asm.loop.controllers[0] = None
        asm.loop._adopt(0, ctrl)
    start(asm, "off")
    try:
        lp = asm.loop
        y0 = float(asm.driver.position_m[0])
        x0 = lp.programs[0].sample(0.0)[0]
        lp.start_axis(0, Move(y0, x0, 0.1, 2.0, 200.0))
        lp.run(CYCLES // 2)
        lp.stop_axis(0)
        lp.run(CYCLES // 4)
        asm.driver.inject("nan", "X", cycles=1)        # a fault: 0 V, amplifier off, IDLE
        lp.run(CYCLES // 4)
    finally:
        shutdown(asm)
    assert (asm.loop.ax[0, A_LAW] == LAW_PY) == python_law
    return asm.loop.rows()


@pytest.mark.parametrize("law", ["c2", "pid", "c2-compensated"])
def test_a_compiled_law_and_the_same_law_from_python_record_the_same(repo, law):
    compiled = _record(repo, law, python_law=False)
    from_python = _record(repo, law, python_law=True)
    lay = RecordLayout(["X"])
    timing = {lay.cycle(f) for f in ("lateness_ns", "turnaround_ns", "read_ns", "control_ns", "write_ns")}
    keep = [j for j in range(compiled.shape[1]) if j not in timing]
    assert compiled.shape == from_python.shape
    assert np.array_equal(compiled[:, keep], from_python[:, keep], equal_nan=True)
    e = compiled[:, lay.index("X.e")]
    assert np.nanmax(np.abs(e)) > 1e-6                 # it tracked something
    assert compiled[-1, lay.index("X.fault_bits")] != 0   # and the fault latched
    if law == "c2-compensated":                        # the compensation acted
        plain = _record(repo, "c2", python_law=False)
        assert not np.allclose(plain[:, lay.index("X.u")], compiled[:, lay.index("X.u")])


@pytest.mark.parametrize("case", ["compiled", "x-with-a-hook", "x-with-effect-terms"])
def test_the_compiled_plants_draw_the_same_noise_as_one_draw_at_a_time(repo, case):
    """x-with-a-hook: X's plant has an input delay (an effect hook: its input transform runs in
    Python, then its period is one compiled call of its own) and the driver's read and write run
    per axis; its noise must still be the Generator's draws, one at a time from the first.
    x-with-effect-terms: X's plant has cogging and a Stribeck curve, whose compiled terms run
    inside the driver's one compiled write; the same positions as their Python hooks."""
    d = load_yaml(repo / "configs" / "gantry.yaml")
    delayed = case == "x-with-a-hook"
    if delayed:
        d["axes"]["X"]["driver"]["input_delay_s"] = 0.0004
    if case == "x-with-effect-terms":
        d["axes"]["X"]["driver"]["effects"] = {**EXAMPLES["cogging"], **EXAMPLES["stribeck"]}
    loaded = config_from_dict(d, "gantry")
    fast, slow = loaded.make_driver(), loaded.make_driver()
    assert fast._compiled != delayed
    seeds = np.random.default_rng(loaded.driver_options.seed).integers(0, 2**63 - 1, size=len(slow.plants))
    slow._compiled = False
    for p, s in zip(slow.plants, seeds):
        p._compiled = False                            # the Python step, one draw at a time
        p._terms = None                                # the effects' Python hooks
        p.rng = np.random.default_rng(int(s))
    n = len(fast.axis_names)
    rng = np.random.default_rng(3)                     # derandomized
    on = np.ones(n, dtype=bool)
    deferred = 0
    for k in range(3000):
        u = rng.uniform(-3.0, 3.0, n) if k % 700 < 600 else np.zeros(n)   # stiction holds it at rest
        for d in (fast, slow):
            d.write(u, on)
            d.read()
        assert np.array_equal(fast.position_m, slow.position_m), k
        if k % 2 and not delayed:                      # the noise refill between cycles (service),
            deferred += fast._refill                   # or, on even k, first thing in the next write
            fast.service()
            assert not fast._refill
    assert fast.position_m[0] != slow.plants[0].opt.initial_position_m
    assert delayed or deferred > 0                     # some refills did wait for service()


@pytest.mark.parametrize("law", ["c2", "c2-compensated", "pid"])
def test_the_rehearsal_writes_nothing_and_computes_the_next_cycle(repo, law):
    """warm_caches: the spin tail runs the next cycle and the driver's exchange on copies. The
    loop's and the driver's arrays are left as they were (to the bit), and the rehearsed cycle
    computes what the real one then does from the same reading: the same output and record."""
    from motorctl.loop import cycle as C
    d = load_yaml(repo / "configs" / "gantry.yaml")
    if law == "c2-compensated":
        d["axes"]["X"]["controller"]["compensation"] = COMPENSATION
    loaded = config_from_dict(d, "gantry")
    asm = build(loaded, None, "pid" if law == "pid" else "c2", clock="virtual", capacity=1000)
    start(asm, "off")
    try:
        lp, drv = asm.loop, asm.driver
        lp.run(3000)                                    # 0.6 s: X moving (its first move at 0.5 s)
        copies = lp._cycle_arrays(copies=True)
        st, scratch = lp._cycle_state(), C.cycle_state(*copies)
        fields = dict(zip(C.CYCLE_FIELDS, copies))
        real = [a.copy() for a in (lp.ax, lp.axf, lp._cf, lp._ci, lp._cl, lp._sig, lp.supervisor.si,
                                   lp.supervisor.sf, lp.u_out, lp.enable_out, lp.buf, drv._S, drv._NZ,
                                   drv.position_m, drv.applied_u, drv.amp_enabled)]
        drv.rehearse(lp.u_out, lp.enable_out)
        C.rehearse(lp._cycle, C.refresh, C.CYCLE_ALL, lp.k, st, scratch)
        after = (lp.ax, lp.axf, lp._cf, lp._ci, lp._cl, lp._sig, lp.supervisor.si, lp.supervisor.sf,
                 lp.u_out, lp.enable_out, lp.buf, drv._S, drv._NZ, drv.position_m, drv.applied_u,
                 drv.amp_enabled)
        for a, b in zip(real, after):
            assert np.array_equal(a, b, equal_nan=True)
        rehearsed_u = fields["uo"].copy()
        rehearsed_row = fields["buf"][0].copy()
        k = lp.k
        lp._cycle(C.CYCLE_ALL, k, st)                   # the real cycle, on the same reading
        assert np.array_equal(lp.u_out, rehearsed_u)
        own = [j for j in range(lp.width) if j not in lp._o_cycle]   # not the loop's timing
        assert np.array_equal(lp.buf[k % lp.capacity][own], rehearsed_row[own], equal_nan=True)
        assert np.any(lp.u_out != 0.0)
        reading = drv._scratch[0].copy()                # the driver's rehearsed read (pos) ...
        drv.read()
        assert np.array_equal(drv.position_m, reading)  # ... is the real one
    finally:
        shutdown(asm)


def test_a_wall_clock_run_gives_the_same_figures_with_and_without_the_rehearsal(repo):
    """The rehearsal changes timing only: a wall-clock run (its indexes depend on the cycle count,
    not on the host's timing) gives the same figures to the bit with warm_caches on and off."""
    from motorctl.app.job import run_job
    figures = []
    for warm in (True, False):
        d = load_yaml(repo / "configs" / "gantry.yaml")
        d["loop"]["realtime"].update(policy="off", warm_caches=warm)
        r = run_job(config_from_dict(d, "gantry"), duration_s=0.3, clock="wall")
        figures.append({a: (v["e_M_um"], v["L2_um"], v["u_peak_V"], v["fault"]) for a, v in r.axes.items()})
    assert figures[0] == figures[1]
    assert figures[0]["X"][0] > 0.0


#: a fresh interpreter with numba's allocation counter on: the allocations of N loop cycles and of
#: N rehearsals (each counted once before and once after N more, so what a run() costs once cancels)
_ALLOC_PROBE = """
import sys
from numba.core.runtime import rtsys
from motorctl.app.build import build, shutdown, start
from motorctl.config import config_from_dict, load_yaml
from motorctl.loop import cycle as C
d = load_yaml(sys.argv[1])
if sys.argv[3]:
    d["axes"]["X"]["controller"]["compensation"] = eval(sys.argv[3])
asm = build(config_from_dict(d, "gantry"), None, sys.argv[2], clock="virtual", capacity=1000)
start(asm, "off")
lp, drv = asm.loop, asm.driver
lp.run(3000)
st, scratch = lp._cycle_state(), lp._cycle_state(copies=True)
def allocs(n):
    a = rtsys.get_allocation_stats().alloc
    lp.run(n)
    for _ in range(n):
        drv.rehearse(lp.u_out, lp.enable_out)
        C.rehearse(lp._cycle, C.refresh, C.CYCLE_ALL, lp.k, st, scratch)
    return rtsys.get_allocation_stats().alloc - a
print(allocs(2000) - allocs(1000))
shutdown(asm)
"""


@pytest.mark.parametrize("law", ["c2", "c1", "pid", "c2-compensated"])
def test_the_loop_cycle_and_its_rehearsal_allocate_nothing(repo, law):
    """Nothing allocates inside the cycle: numba's runtime counts no allocation per cycle of the
    loop on the simulated driver (read, the compiled cycle, write with each plant's period) nor
    per rehearsal (NUMBA_NRT_STATS in a fresh interpreter; 1000 more cycles cost 0 more)."""
    import os
    import subprocess
    import sys
    comp = repr(COMPENSATION) if law == "c2-compensated" else ""
    out = subprocess.run([sys.executable, "-c", _ALLOC_PROBE, str(repo / "configs" / "gantry.yaml"),
                          "c2" if law == "c2-compensated" else law, comp],
                         env={**os.environ, "NUMBA_NRT_STATS": "1"}, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert int(out.stdout.split()[-1]) == 0, out.stdout


def test_a_borrowed_view_reads_and_writes_its_owner():
    """motorctl.jit.borrow keeps the view's data, shape and strides (only its reference to the
    owner is dropped): the law's matrix views written through it land in the owner's buffer,
    row-major, and a 1-D borrowed slice reads what the owner holds."""
    from motorctl.control.dcdiarc import _matrix
    from motorctl.jit import borrow, njit

    @njit
    def fill(buf, at, rows, cols):
        m = borrow(_matrix(buf, at, rows, cols))
        for i in range(rows):
            for j in range(cols):
                m[i, j] = 10.0 * i + j
        v = borrow(buf[at + cols:at + 2 * cols])
        return m.shape[0], m.shape[1], v.sum()

    buf = np.zeros(20)
    rows, cols, s = fill(buf, 4, 3, 2)
    assert (rows, cols) == (3, 2)
    assert buf[4:10].tolist() == [0.0, 1.0, 10.0, 11.0, 20.0, 21.0]
    assert buf[:4].tolist() == [0.0] * 4 and buf[10:].tolist() == [0.0] * 10
    assert s == 21.0
