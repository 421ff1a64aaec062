"""The per-axis status block the loop publishes (between cycles) in the shared ring, and the
status the I/O process builds from it for ``motorctl status``.

Status block (float64 per axis, :data:`ST_FIELDS` in order): the sequencing mode, the active
controller (its index in :data:`motorctl.control.CONTROLLER_NAMES`), the latched fault bits,
the value and the limit at the fault, the I/O error count, the following-error peak and the
cycle of the last start, the home switch (1: active) and the index latch [m] (NaN: none) of
a driver with homing inputs (the simulated one), the I²t level (the accumulator over its trip
level: 1 trips FAULT_I2T).
"""

from __future__ import annotations

import math

from motorctl.control import CONTROLLER_NAMES
from motorctl.loop.records import RecordLayout
from motorctl.loop.safety import FAULT_RECORDER, describe_faults
from motorctl.loop.servo import IDLE, MODE_NAMES

ST_FIELDS = ("mode", "controller", "fault", "value", "limit", "io_errors", "fe_peak", "started_k",
             "home_switch", "index_latch", "i2t")
ST = {name: j for j, name in enumerate(ST_FIELDS)}
ST_SIZE = len(ST_FIELDS)


class StatusPublisher:
    """Loop side: writes the status block of every axis (outside the timed cycle).

    Args:
        status: (n_axes, ST_SIZE) float64 shared array. loop: the ServoLoop. active: the
        list of active controller names per axis (kept up to date by the loop side).
    """

    def __init__(self, status, loop, active: list):
        self._mv = memoryview(status.reshape(-1))
        self.loop, self.active = loop, active
        self.started_k = [0] * len(active)
        self._published_fault = [0] * len(active)

    def publish(self) -> None:
        mv, lp, sup = self._mv, self.loop, self.loop.supervisor
        sw = getattr(lp.driver, "home_switch", None)
        latch = getattr(lp.driver, "index_latch_m", None)
        for i in range(len(self.active)):
            self._published_fault[i] = sup.fault[i]
            b = i * ST_SIZE
            mv[b + ST["mode"]] = float(lp.mode[i])
            mv[b + ST["controller"]] = float(CONTROLLER_NAMES.index(self.active[i]))
            mv[b + ST["fault"]] = float(sup.fault[i])
            mv[b + ST["value"]] = sup.value_at_fault[i]
            mv[b + ST["limit"]] = sup.limit_at_fault[i]
            mv[b + ST["io_errors"]] = float(sup.io_errors[i])
            mv[b + ST["fe_peak"]] = sup.fe_peak[i]
            mv[b + ST["started_k"]] = float(self.started_k[i])
            mv[b + ST["home_switch"]] = float(sw[i]) if sw is not None else 0.0
            mv[b + ST["index_latch"]] = float(latch[i]) if latch is not None else math.nan
            lim = sup.i2t_limit[i]
            mv[b + ST["i2t"]] = sup.i2t[i] / lim if lim > 0 else 0.0

    def fault_changed(self) -> bool:
        """True when a fault latched or cleared since the last :meth:`publish`."""
        fault = self.loop.supervisor.fault
        return any(fault[i] != self._published_fault[i] for i in range(len(self.active)))


def fault_text(bits: int, value: float, limit: float, recorder: str = "") -> str:
    """One line for latched fault bits: their names, the value and limit of the first one,
    and for FAULT_RECORDER why (``recorder``, e.g. "log disk full"); "" when no fault."""
    if not bits:
        return ""
    if bits == FAULT_RECORDER:
        return f"{describe_faults(bits)}: {recorder or 'fault'}"
    text = f"{describe_faults(bits)} (value {value:.6g}, limit {limit:.6g})"
    return text + (f"; recorder: {recorder}" if bits & FAULT_RECORDER and recorder else "")


def axis_status(i: int, name: str, status_row, row, layout: RecordLayout, recorder: str = "") -> dict:
    """I/O side: one axis's status from its status block and the newest record row (or
    None before the first cycle); ``recorder``: why FAULT_RECORDER latched (if it did)."""
    bits = int(status_row[ST["fault"]])
    mode = int(status_row[ST["mode"]])
    out = {"axis": name,
           "state": "fault" if bits else ("disabled" if mode == IDLE else "enabled"),
           "phase": MODE_NAMES.get(mode, "?"),
           "fault_bits": bits,
           "fault": fault_text(bits, status_row[ST["value"]], status_row[ST["limit"]], recorder),
           "controller": CONTROLLER_NAMES[int(status_row[ST["controller"]])]}
    if row is not None:
        def f(field):
            return float(row[layout.index(f"{name}.{field}")])
        theta = [f(f"theta_hat{j}") for j in range(1, 7)]
        out.update(y_m=f("y"), x_d_m=f("x_d"), following_error_m=f("e"), u_V=f("u"),
                   theta_hat=[x for x in theta if not math.isnan(x)], d_hat0_V=f("d_hat0"),
                   amplifier_enabled=bool(f("enabled")))
    else:
        out.update(y_m=float("nan"), following_error_m=float("nan"))
    out["following_error_peak_m"] = float(status_row[ST["fe_peak"]])
    out["io_errors"] = int(status_row[ST["io_errors"]])
    out["i2t_level"] = float(status_row[ST["i2t"]])
    return out
