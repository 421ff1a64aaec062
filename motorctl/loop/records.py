"""The cycle record, declared once by name (and unit): what the loop writes every cycle.

One float64 row per cycle: the cycle-wide fields, then for every axis the axis fields under
``AXIS.<field>``, then the signals the axes' laws declare of their own
(:attr:`motorctl.control.base.Controller.own_signals`), under ``AXIS.<signal>``, axis by axis,
then the machine outputs the loop applied in that cycle under ``out.<name>`` (the outputs of a
setpoint ring, :mod:`motorctl.loop.stream`; none without one): a row without them is the same
row up to its last axis field, so a reader that knows only the fixed fields reads any log. The
loop, the flight recorder, the daemon's status, the run-log reader, the
exporters and the plots all index a row by these names through :class:`RecordLayout`, never by
a hand-counted offset.

The controller block (:data:`motorctl.control.signals.CONTROLLER_SIGNALS`) is what every
controller publishes after each sample (:class:`motorctl.control.base.Controller`); a signal a controller does not have
(θ̂5/θ̂6 for C1, θ̂ and d̂0 for a PID) is NaN, never a stale value of another controller.
"""

from __future__ import annotations

from motorctl.control.signals import CONTROLLER_SIGNALS, N_SIGNALS, N_THETA_MAX  # noqa: F401  (the record's layout)

#: cycle-wide fields: name -> unit
CYCLE_FIELDS: dict[str, str] = {
    "t": "s",                  # program time k·Ts of this cycle
    "lateness_ns": "ns",       # wake − deadline
    "turnaround_ns": "ns",     # read start → write end
    "read_ns": "ns",
    "control_ns": "ns",
    "write_ns": "ns",
    "overruns": "1",           # missed periods so far
}

#: the controller block: declared with the laws (:mod:`motorctl.control.signals`)

#: per-axis fields: name -> unit. The controller block is contiguous (the loop copies it).
AXIS_FIELDS: dict[str, str] = {
    "y": "m",
    "x_d": "m",
    "xd_dot": "m/s",
    "xd_ddot": "m/s^2",
    "u": "V",
    **CONTROLLER_SIGNALS,
    "enabled": "1",            # amplifier enable written this cycle
    "fault_bits": "1",         # latched fault bits (motorctl.loop.safety)
    "mode": "1",               # the sequencer's mode: 0 idle, 1 approach, 2 program, 3 hold, 4 jog
}
#: the prefix of an output's column
OUTPUT_PREFIX = "out."
#: the ``mode`` field's codes (motorctl.loop.cycle's IDLE ... JOG)
MODE_IDLE, MODE_APPROACH, MODE_PROGRAM, MODE_HOLD, MODE_JOG = range(5)


class RecordLayout:
    """Column names, units and offsets of the record for a list of axes.

    Args:
        axis_names: axes in loop order.
        own: axis -> {signal name: unit} of the signals its laws declare of their own
            (:attr:`motorctl.control.base.Controller.own_signals`), recorded after every axis's
            fixed fields; None or missing axes: none.
        outputs: machine output names (the columns ``out.NAME`` after the own signals, unit
            "1": 0/1 for a digital output, the S value for a power output).
    Attributes:
        columns (list[str]): ``t, lateness_ns, ..., X.y, X.x_d, ..., X.<own signal>, ...,
            out.torch``; width = len(columns).
        units (list[str]): the unit of every column.
        own (dict[str, dict[str, str]]): the own signals by axis (every axis a key).
        own_start (int): offset of the first own-signal column.
        outputs (tuple[str, ...]); outputs_base (int): offset of the first output column (=
            width without outputs).
    Raises:
        ValueError: an own signal named like a fixed axis field.
    """

    def __init__(self, axis_names, own=None, outputs=()):
        self.axis_names = list(axis_names)
        self.own = {a: dict((own or {}).get(a, {})) for a in self.axis_names}
        self.columns = list(CYCLE_FIELDS)
        self.units = list(CYCLE_FIELDS.values())
        for a in self.axis_names:
            self.columns += [f"{a}.{f}" for f in AXIS_FIELDS]
            self.units += list(AXIS_FIELDS.values())
        self.own_start = len(self.columns)
        for a, sigs in self.own.items():
            clash = [f for f in sigs if f in AXIS_FIELDS]
            if clash:
                raise ValueError(f"axis {a}: own signal {clash[0]!r} is a fixed axis field; fields: "
                                 f"{', '.join(AXIS_FIELDS)}")
            self.columns += [f"{a}.{f}" for f in sigs]
            self.units += list(sigs.values())
        self.outputs_base = len(self.columns)
        self.outputs = tuple(outputs)
        self.columns += [f"{OUTPUT_PREFIX}{o}" for o in self.outputs]
        self.units += ["1"] * len(self.outputs)
        self.width = len(self.columns)
        self._index = {c: j for j, c in enumerate(self.columns)}

    def cycle(self, field: str) -> int:
        """Offset of a cycle-wide field in a row. Raises KeyError for an unknown field."""
        if field not in CYCLE_FIELDS:
            raise KeyError(f"no cycle field {field!r}; fields: {', '.join(CYCLE_FIELDS)}")
        return self._index[field]

    def axis_base(self, i: int) -> int:
        """Offset of axis i's first field in a row."""
        return len(CYCLE_FIELDS) + i * len(AXIS_FIELDS)

    @staticmethod
    def axis_field(field: str) -> int:
        """Offset of a per-axis field from the axis's base. Raises KeyError if unknown."""
        try:
            return list(AXIS_FIELDS).index(field)
        except ValueError:
            raise KeyError(f"no axis field {field!r}; fields: {', '.join(AXIS_FIELDS)}") from None

    def index(self, column: str) -> int:
        """Offset of a full column name (``"t"``, ``"X.u"``). Raises KeyError if unknown."""
        try:
            return self._index[column]
        except KeyError:
            raise KeyError(f"no column {column!r}; columns: {', '.join(self.columns)}") from None

    def header(self) -> dict:
        """The layout's part of a run-log header: ``columns`` and ``units``."""
        return {"columns": list(self.columns), "units": list(self.units)}


def columns_for(axis_names) -> list[str]:
    """Column names of a record for these axes (order of the row)."""
    return RecordLayout(axis_names).columns
