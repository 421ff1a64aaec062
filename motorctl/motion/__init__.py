"""Motion from part programs: a G-code reader, a look-ahead path planner and the ISO 230-4
circular test.

A pure library (no loop, no daemon): :func:`motorctl.motion.gcode.parse` turns a G-code text into a
:class:`~motorctl.motion.gcode.Program` of segments in metres (machine coordinates),
:func:`motorctl.motion.planner.check_limits` checks it against the soft limits,
:func:`motorctl.motion.planner.plan` turns it into a jerk-limited
:class:`~motorctl.motion.planner.Trajectory` the I/O side samples into the loop's setpoint ring, and
:func:`motorctl.motion.planner.point_to_point` plans a coordinated straight move.
"""

from motorctl.motion.gcode import (Arc, Dwell, Event, GcodeError, GcodeSettings, Line, Pause, Program,
                                   parse)
from motorctl.motion.path import contour_error
from motorctl.motion.planner import (AxisLimits, LimitError, Trajectory, check_limits, headroom, plan,
                                     point_to_point)

__all__ = ["Arc", "AxisLimits", "Dwell", "Event", "GcodeError", "GcodeSettings", "LimitError", "Line",
           "Pause", "Program", "Trajectory", "check_limits", "contour_error", "headroom", "parse", "plan",
           "point_to_point"]
