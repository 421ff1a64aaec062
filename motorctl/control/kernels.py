"""The built-in laws' compiled steps, chosen by code, for the compiled servo cycle.

:mod:`motorctl.loop.cycle` keeps each axis's law state in its rows (``f`` float64, ``ii``
int64, ``lay`` int64 (N_LAYOUT,), ``sig`` (N_SIGNALS,); :meth:`Controller.attach` puts it
there) and calls :func:`law_step` / :func:`law_reset` with the axis's law code
(:data:`motorctl.control.base.LAW_DCDIARC`, ``LAW_DCDIARC_COMP``, ``LAW_PID``). A law without
a compiled step (LAW_PY: a law from another package) is run by the cycle from Python through
:meth:`Controller.update`. :data:`LAW_KERNELS` is the one table from a code to its compiled
step; :func:`check_law_code` refuses any other code when the loop takes the law (at build and
at a switch), so the compiled dispatch never meets an unknown code (if it did, the output
would be NaN, which the supervisor faults, never another law's step).

numba caches these steps with what they call compiled in (the compensation's dispatch over its
code -> kernel table, :mod:`motorctl.effects.compensation`), keyed on this module's source only;
motorctl's cache folder is keyed by all of its sources (:mod:`motorctl.jitcache`), so a change
of that table or of a kernel it holds gives a cold cache, which compiles them afresh.
"""

from __future__ import annotations

import numpy as np

from motorctl.control.base import LAW_DCDIARC, LAW_DCDIARC_COMP, LAW_GTCF, LAW_PID, LAW_PY
from motorctl.control.dcdiarc import B_CT, N_LAYOUT, dcdiarc_block_reset, dcdiarc_block_step, dcdiarc_comp_step
from motorctl.control.gtcf import gtcf_reset
from motorctl.control.pid import N_PRM as PID_N_PRM
from motorctl.control.pid import N_STATE as PID_N_STATE
from motorctl.control.pid import pid_reset, pid_step
from motorctl.effects.compensation import T_PREVIEW
from motorctl.jit import borrow, njit

__all__ = ["LAW_DCDIARC", "LAW_DCDIARC_COMP", "LAW_GTCF", "LAW_KERNELS", "LAW_PID", "LAW_PY", "N_LAYOUT", "check_law_code",
           "law_preview", "law_reset", "law_step"]

#: law code -> what the servo cycle runs for it: the compiled step of :func:`law_step` (and
#: :func:`law_reset`), or, for LAW_PY, the law's :meth:`Controller.update` from Python
LAW_KERNELS: dict[int, str] = {
    LAW_PY: "Controller.update from Python",
    LAW_DCDIARC: "dcdiarc_block_step",
    LAW_DCDIARC_COMP: "dcdiarc_comp_step (with the compensation's compiled terms)",
    LAW_PID: "pid_step",
    LAW_GTCF: "gtcf_step (a pair: the cycle passes the partner axis's sample, motorctl.loop.cycle)",
}


def check_law_code(code: int, law: str) -> int:
    """``code`` when the servo cycle has a step for it (a key of :data:`LAW_KERNELS`).

    Raises:
        ValueError: an unknown code, naming the law ``law`` and the known codes.
    """
    if isinstance(code, bool) or not isinstance(code, int) or code not in LAW_KERNELS:
        known = ", ".join(f"{k} ({v})" for k, v in LAW_KERNELS.items())
        raise ValueError(f"controller {law!r}: law_code {code!r} has no step in the servo cycle; known: {known}")
    return code


@njit
def law_preview(law, f, lay):
    """How far ahead [s] law ``law`` wants the desired trajectory (its input delay τ; 0: never)."""
    if law == LAW_DCDIARC_COMP or law == LAW_GTCF:
        return f[lay[B_CT] + T_PREVIEW]
    return 0.0


@njit
def law_step(law, y, x_d, xd_dot, xd_ddot, xf, vf, af, t, sig, f, ii, lay):
    """One sample of axis law ``law`` on its rows: measured position y [m], desired position
    [m], velocity [m/s] and acceleration [m/s²], the same at t + :func:`law_preview` (xf, vf,
    af) and the time t [s]; returns u [V] (paper eq. 9-19 for LAW_DCDIARC, with the
    compensation's terms for LAW_DCDIARC_COMP, LinuxCNC's pid for LAW_PID), the signals written
    into sig."""
    if law == LAW_DCDIARC:
        return dcdiarc_block_step(y, x_d, xd_dot, xd_ddot, x_d, xd_dot, xd_ddot, 0.0, 1.0, 1.0, sig, f, ii, lay, 0.0)
    if law == LAW_DCDIARC_COMP:
        return dcdiarc_comp_step(y, x_d, xd_dot, xd_ddot, xf, vf, af, t, sig, f, ii, lay, 0.0)
    if law == LAW_PID:
        return pid_step(y, x_d, xd_dot, xd_ddot, sig, borrow(f[:PID_N_STATE]),
                        borrow(f[PID_N_STATE:PID_N_STATE + PID_N_PRM]))
    return np.nan       # not reached (check_law_code); a NaN output faults the axis


@njit
def law_reset(law, y0, f, lay):
    """Bumpless (re)start of axis law ``law`` from the measured position y0 [m]."""
    if law == LAW_DCDIARC or law == LAW_DCDIARC_COMP:
        dcdiarc_block_reset(y0, f, lay)
    elif law == LAW_PID:
        pid_reset(y0, borrow(f[:PID_N_STATE]))
    elif law == LAW_GTCF:
        gtcf_reset(y0, f, lay)
