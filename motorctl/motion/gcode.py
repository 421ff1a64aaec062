"""A G-code reader with LinuxCNC's (rs274ngc) semantics for the subset a gantry runs.

:func:`parse` reads a whole program and returns a :class:`Program`: a list of segments
(:class:`Line`, :class:`Arc`, :class:`Dwell`, :class:`Pause`, :class:`Event`) in machine
coordinates, metres and metres per second, each with its source line. Anything outside the subset
raises :class:`GcodeError` naming ``file:line:column``, the word, and what would accept it; a
program that raises yields nothing (the caller queues nothing).

Accepted (semantics of the LinuxCNC G-code reference, "G Codes" and "M Codes" chapters):

- ``G0`` ``G1`` ``G2`` ``G3`` (arcs in the XY plane, centre by ``I J`` (incremental, ``G91.1``; or
  absolute ``G90.1``) or radius ``R`` (negative R: the arc over 180°), ``P`` turns, ``Z`` helix),
  ``G4 P`` (dwell, seconds), ``G17``, ``G20``/``G21``, ``G90``/``G91``, ``G94``, ``G61``/``G61.1``
  (exact stop), ``G64 [P] [Q]`` (blend tolerance P; Q, LinuxCNC's naive-CAM tolerance, P when not
  given: ``Line.naive_cam``), ``G53`` (this line in machine coordinates), ``G54``-``G59``,
  ``G59.1``-``G59.3``, ``G10 L2 P`` (set a work offset), ``G92``/``G92.1``, ``G28`` (through the
  given point to the configured reference point), ``G40``/``G49``/``G80`` (cancel words: nothing
  they cancel can be active here), ``F``, ``N``, ``%`` lines, comments ``( )`` and ``;``, upper and
  lower case, numbers such as ``X.5`` and ``X-0.500``;
- ``M0``/``M1`` (program stop / optional stop, :class:`Pause`), ``M2``/``M30`` (end), and the machine
  words ``M3``/``M4``/``M5``, ``S``, ``M7``/``M8``/``M9``, ``M62``-``M65 P`` as :class:`Event`\\ s where
  :class:`GcodeSettings` maps them to an output or to ``ignore``.

Refused: everything else (``G18``/``G19``, cutter and tool-length compensation, canned cycles,
inverse-time feed, tool changes, parameters ``#``, expressions ``[ ]``, ``O`` subroutines, block
delete ``/``), and any machine word with no mapping.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field

from motorctl.schema import StrictModel

#: the axes a program may name, in the order of a position vector (index 0, 1, 2)
AXES = ("X", "Y", "Z")
#: metres per program unit: G21 (mm), G20 (inch)
MM = 1e-3
INCH = 25.4e-3
#: LinuxCNC's tolerance on the two radii of a centre-format arc: refused if they differ by more than
#: 0.002 mm and by more than 0.1 % (rs274ngc arc_data_ijk)
ARC_RADIUS_TOL_M = 0.002e-3
ARC_RADIUS_TOL_REL = 0.001
#: the machine words a ``gcode:`` config can map
MACHINE_WORDS = ("M3", "M4", "M5", "S", "M7", "M8", "M9", "M62", "M63", "M64", "M65")
#: work coordinate systems by P number of G10 L2 (1 = G54 ... 9 = G59.3)
SYSTEMS = ("G54", "G55", "G56", "G57", "G58", "G59", "G59.1", "G59.2", "G59.3")


class GcodeError(ValueError):
    """A program outside the subset. ``str()`` is one line: ``file:line:column: word: why; what
    would accept it``. Attributes: filename, line (1-based), column (1-based), word."""

    def __init__(self, filename: str, line: int, column: int, word: str, why: str):
        self.filename, self.line, self.column, self.word, self.why = filename, line, column, word, why
        super().__init__(f"{filename}:{line}:{column}: {word}: {why}" if word else
                         f"{filename}:{line}:{column}: {why}")


class GcodeSettings(StrictModel):
    """The ``gcode:`` section of a config.

    words: machine word (``M3``, ``M4``, ``M5``, ``S``, ``M7``, ``M8``, ``M9``, ``M62``-``M65``) →
        the name of a driver output it sets, or ``ignore`` (read, warned about, no effect). A word
        missing here is refused. ``M62``/``M63`` set (1) / clear (0) output ``<name>`` ``P`` at the
        planned point of the path, ``M64``/``M65`` at once; ``M3``/``M4`` set their output to 1,
        ``M5`` sets the ``M3`` and ``M4`` outputs to 0, ``M7``/``M8`` 1 and ``M9`` both 0; ``S`` sets its
        output to the S value.
    reference_point_m: machine coordinates of the G28 reference point per axis [m] (axes not
        named: 0).
    optional_stop: M1 pauses the program (else it is read and passes).
    axes: the axes programs may name (a word for another axis is refused).
    """

    words: dict[str, str] = Field(default_factory=dict)
    reference_point_m: dict[str, float] = Field(default_factory=dict)
    optional_stop: bool = False
    axes: list[Literal["X", "Y", "Z"]] = Field(default_factory=lambda: ["X", "Y", "Z"])

    def model_post_init(self, _ctx) -> None:
        words = {}
        for k, v in self.words.items():
            if _norm_m(k) not in MACHINE_WORDS:
                raise ValueError(f"gcode.words: {k!r} is not a machine word that can be mapped "
                                 f"(allowed: {', '.join(MACHINE_WORDS)})")
            words[_norm_m(k)] = v
        # an output a word switches on must not be left on by its off word being ignored
        for off, ons in (("M5", ("M3", "M4")), ("M9", ("M7", "M8")), ("M63", ("M62",)), ("M65", ("M64",))):
            on = [w for w in ons if words.get(w, "ignore") != "ignore"]
            if on and words.get(off) == "ignore":
                raise ValueError(f"gcode.words.{off}: 'ignore' would leave the output of {on[0]} "
                                 f"({words[on[0]]}) on; map {off} to it")


#: the digital outputs M62-M65 address, P 0 .. N_DIO − 1 (LinuxCNC's default num_dio)
N_DIO = 4
#: the machine words whose outputs are off whenever the motion stops on its own (an underrun, a
#: fault, a stop) or is aborted: spindle/torch, its power, coolant (LinuxCNC's abort turns them off)
STOP_WORDS = ("M3", "M4", "M5", "S", "M7", "M8", "M9")


def output_names(settings: GcodeSettings) -> tuple[list[str], list[str]]:
    """The machine outputs a config's ``gcode:`` section can switch, and those of them that go
    off when the motion stops on its own or is aborted (:data:`STOP_WORDS`): (outputs, stop
    outputs), names in the order of ``words``; M62-M65 to ``name`` give ``name0`` ..
    ``name{N_DIO-1}``."""
    outs: list[str] = []
    stop: list[str] = []
    for word, out in settings.words.items():
        w = _norm_m(word)
        if out == "ignore":
            continue
        names = [f"{out}{p}" for p in range(N_DIO)] if w in ("M62", "M63", "M64", "M65") else [out]
        for o in names:
            if o not in outs:
                outs.append(o)
            if w in STOP_WORDS and o not in stop:
                stop.append(o)
    return outs, stop


def _norm_m(word: str) -> str:
    """``M03`` → ``M3``, ``m62`` → ``M62``, ``s`` → ``S``."""
    w = word.strip().upper()
    if w.startswith("M") and w[1:].isdigit():
        return f"M{int(w[1:])}"
    return w


# --------------------------------------------------------------------------------------- segments
@dataclass(frozen=True)
class Line:
    """A straight move from ``start`` to ``end`` (shape (3,), X Y Z machine coordinates [m]).

    feed: path speed [m/s]; None for a rapid (G0: each axis's own limits). tolerance: the blend
    tolerance at its end [m] (0: exact stop, G61; inf: G64 without P). line: source line (1-based).
    naive_cam: G64's Q [m], LinuxCNC's naive-CAM tolerance: consecutive straight feed moves whose
    points lie within it of one line may be run as that line (0: none; Q defaults to P).
    """

    start: np.ndarray
    end: np.ndarray
    feed: float | None
    tolerance: float
    line: int
    naive_cam: float = 0.0

    @property
    def length(self) -> float:
        """Path length [m]."""
        return float(np.linalg.norm(self.end - self.start))


@dataclass(frozen=True)
class Arc:
    """A circular (helical with Z) move in the XY plane from ``start`` to ``end`` about ``center``
    (each shape (3,), machine coordinates [m]; center[2] = start[2]).

    cw: clockwise seen from +Z (G2). turns: full turns beyond the first (P − 1). feed [m/s],
    tolerance [m] and line as :class:`Line`.
    """

    start: np.ndarray
    end: np.ndarray
    center: np.ndarray
    cw: bool
    turns: int
    feed: float
    tolerance: float
    line: int

    @property
    def radius(self) -> float:
        """Radius at the start [m]."""
        return float(math.hypot(*(self.start[:2] - self.center[:2])))

    @property
    def sweep(self) -> float:
        """Signed angle swept [rad] (negative clockwise); a full circle when start = end in XY."""
        a0 = math.atan2(self.start[1] - self.center[1], self.start[0] - self.center[0])
        a1 = math.atan2(self.end[1] - self.center[1], self.end[0] - self.center[0])
        d = a1 - a0
        if self.cw:
            d = -((-d) % (2 * math.pi))
            if d == 0.0:
                d = -2 * math.pi
            return d - 2 * math.pi * self.turns
        d = d % (2 * math.pi)
        if d == 0.0:
            d = 2 * math.pi
        return d + 2 * math.pi * self.turns

    @property
    def length(self) -> float:
        """Path length [m] (helix included)."""
        r_end = float(math.hypot(*(self.end[:2] - self.center[:2])))
        planar = abs(self.sweep) * 0.5 * (self.radius + r_end)
        return float(math.hypot(planar, self.end[2] - self.start[2]))


@dataclass(frozen=True)
class Dwell:
    """G4: stand still ``seconds`` [s] after the motion before has stopped."""

    seconds: float
    line: int


@dataclass(frozen=True)
class Pause:
    """M0 (``optional`` False) or M1 (True): stop on the path and wait for resume."""

    optional: bool
    line: int


@dataclass(frozen=True)
class Event:
    """A machine word mapped by :class:`GcodeSettings`: set ``output`` to ``value`` (None output:
    ignored, see ``Program.warnings``). synchronized: at the planned point of the path (M62/M63;
    the motion does not stop); otherwise the motion before stops first (M3, M5, S, M7-M9, M64/M65).
    word: the normalised word (``M3``, ``S``, ``M62``); p: the P number of M62-M65."""

    word: str
    output: str | None
    value: float
    synchronized: bool
    line: int
    column: int
    p: int | None = None

    @property
    def target(self) -> str | None:
        """The output switched: ``output``, and for M62-M65 ``output`` followed by the P number
        (``dout`` P2 → ``dout2``); None when ignored."""
        if self.output is None or self.p is None:
            return self.output
        return f"{self.output}{self.p}"


Segment = Line | Arc | Dwell | Pause | Event


@dataclass
class Program:
    """A parsed program: ``segments`` in order, machine coordinates [m], path speeds [m/s].

    start, end: the machine position (shape (3,), X Y Z [m]) before the first and after the last
    segment. warnings: one line each (ignored machine words). offsets: the work offsets at the end
    (``G54`` ... → shape (3,) [m]) and the G92 offset.
    """

    filename: str
    segments: list[Segment]
    start: np.ndarray
    end: np.ndarray
    warnings: list[str] = field(default_factory=list)
    offsets: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def moves(self) -> list[Line | Arc]:
        """The motion segments only."""
        return [s for s in self.segments if isinstance(s, (Line, Arc))]


# --------------------------------------------------------------------------------------- the reader
_NUM = r"[+-]?\s*(?:\d[\d\s]*(?:\.[\d\s]*)?|\.\s*\d[\d\s]*)"
_WORD = re.compile(r"([A-Za-z])\s*(" + _NUM + ")")

#: G words with their modal group (rs274ngc table 5) - only those accepted
_GROUP = {0: "motion", 1: "motion", 2: "motion", 3: "motion", 80: "motion",
          17: "plane", 20: "units", 21: "units", 90: "distance", 91: "distance",
          90.1: "arc_distance", 91.1: "arc_distance", 94: "feed_mode",
          61: "path", 61.1: "path", 64: "path", 40: "cutter", 49: "tool_length",
          54: "cs", 55: "cs", 56: "cs", 57: "cs", 58: "cs", 59: "cs", 59.1: "cs", 59.2: "cs", 59.3: "cs",
          4: "non_modal", 10: "non_modal", 28: "non_modal", 53: "non_modal", 92: "non_modal",
          92.1: "non_modal"}
_REFUSED_G = {18: "the XZ plane (only G17, XY, is supported)", 19: "the YZ plane (only G17, XY)",
              41: "cutter compensation (the CAM program must carry the compensated path)",
              42: "cutter compensation (the CAM program must carry the compensated path)",
              43: "tool length compensation", 93: "inverse-time feed (use G94)",
              28.1: "storing the reference point (set gcode.reference_point_m in the config)"}
_M_GROUP = {0: "stop", 1: "stop", 2: "stop", 30: "stop", 3: "spindle", 4: "spindle", 5: "spindle",
            7: "coolant", 8: "coolant", 9: "coolant", 62: "dio", 63: "dio", 64: "dio", 65: "dio"}
_SUBSET = "see docs/motion.md for the accepted subset"


@dataclass
class _Word:
    letter: str
    value: float
    text: str
    column: int


_BLANK = re.compile(r"\s")
#: a line of straight moves alone (N, G0/G1, then X Y Z F in this order, each at most once; no
#: comment): the reader's fast path, the same semantics as the general one (a line it cannot
#: take whole goes the general way)
_N = r"([-+]?(?:\d+(?:\.\d*)?|\.\d+))[ \t]*"
_SIMPLE = re.compile(r"[ \t]*(?:[Nn]\d+[ \t]*)?(?:[Gg]0*([01])(?![\d.])[ \t]*)?(?:[Xx][ \t]*" + _N + r")?"
                     r"(?:[Yy][ \t]*" + _N + r")?(?:[Zz][ \t]*" + _N + r")?(?:[Ff][ \t]*" + _N + r")?")


def _number(s: str) -> float:
    return float(_BLANK.sub("", s))


def _fmt(v: float) -> str:
    return f"{v:g}"


class _Reader:
    def __init__(self, filename: str, settings: GcodeSettings, start, offsets):
        self.f = filename
        self.s = settings
        self.words_map = {_norm_m(k): v for k, v in settings.words.items()}
        self.pos = np.zeros(3) if start is None else np.array(start, dtype=float).reshape(3).copy()
        self.start = self.pos.copy()
        self.cs = {name: np.zeros(3) for name in SYSTEMS}
        for k, v in (offsets or {}).items():
            if k not in self.cs:
                raise ValueError(f"work offset {k!r}: not a coordinate system (allowed: {', '.join(SYSTEMS)})")
            self.cs[k] = np.array(v, dtype=float).reshape(3).copy()
        self.active = "G54"
        self.g92 = np.zeros(3)
        self.unit = MM
        self.absolute = True
        self.arc_absolute = False
        self.motion: float | None = None
        self.f_word = 0.0                # the F number, in the active units per minute (rs274ngc keeps
                                         # the number across G20/G21)
        self.tol = math.inf              # G64 without P at start (LinuxCNC default G64)
        self.q = 0.0                     # G64 Q (naive-CAM tolerance; P when Q is not given)
        self.ref = np.array([settings.reference_point_m.get(a, 0.0) for a in AXES])
        self.segments: list[Segment] = []
        self.warnings: list[str] = []
        self.done = False

    # errors
    def err(self, line: int, w: _Word | None, why: str, col: int = 1) -> GcodeError:
        return GcodeError(self.f, line, w.column if w else col, w.text if w else "", why)

    @property
    def feed(self) -> float | None:
        """The active feed [m/s] (None: no F yet, or F0)."""
        return self.f_word * self.unit / 60.0 if self.f_word > 0 else None

    def offset(self) -> np.ndarray:
        return self.cs[self.active] + self.g92

    # one source line
    def line(self, n: int, raw: str) -> None:
        if self._simple(n, raw):
            return
        text = self._strip_comments(n, raw)
        if not text.strip():
            return
        words: list[_Word] = []
        pos = 0
        for m in _WORD.finditer(text):
            if m.start() > pos:
                self._stray(n, text, pos, m.start())
            letter, num = m.group(1).upper(), m.group(2)
            if letter == "O":
                raise GcodeError(self.f, n, m.start() + 1, m.group(0).strip(),
                                 f"subroutines and flow control (O words) are not in the subset; {_SUBSET}")
            if _BLANK.search(num):
                num = _BLANK.sub("", num)
            words.append(_Word(letter, float(num), letter + num, m.start() + 1))
            pos = m.end()
        self._stray(n, text, pos, len(text))
        self._block(n, words)

    def _simple(self, n: int, raw: str) -> bool:
        """The fast path of a line of straight moves (:data:`_SIMPLE`): True when it took the
        line, False when the line must go the general way (anything else, or anything the
        general way would refuse or treat otherwise)."""
        m = _SIMPLE.fullmatch(raw)
        if m is None:
            return False
        g, x, y, z, f = m.groups()
        axes = self.s.axes
        if ((x is not None and "X" not in axes) or (y is not None and "Y" not in axes)
                or (z is not None and "Z" not in axes)):
            return False
        motion = self.motion if g is None else int(g)
        f_word = self.f_word if f is None else float(f)
        moves = x is not None or y is not None or z is not None
        if f_word < 0 or (moves and (motion not in (0, 1) or (motion == 1 and not f_word > 0))):
            return False                     # the general way says why
        self.f_word = f_word
        self.motion = motion
        if moves:                            # Python floats, one array (positions are never
            p = self.pos.tolist()            # changed in place: a Line may share them)
            t = list(p)
            base = (self.cs[self.active] + self.g92).tolist() if self.absolute else p
            u = self.unit
            if x is not None:
                t[0] = base[0] + float(x) * u
            if y is not None:
                t[1] = base[1] + float(y) * u
            if z is not None:
                t[2] = base[2] + float(z) * u
            if t != p:
                end = np.array(t)
                self.segments.append(Line(self.pos, end, None if motion == 0 else self.feed, self.tol, n,
                                          0.0 if motion == 0 else self.q))
                self.pos = end
        return True

    def _stray(self, n: int, text: str, a: int, b: int) -> None:
        """Refuse anything but blanks in text[a:b] (between words)."""
        gap = text[a:b]
        if not gap.strip():
            return
        special = [i for i, c in enumerate(gap) if c in "#[/="]
        bad = a + (special[0] if special else len(gap) - len(gap.lstrip()))
        ch = text[bad]
        what = {"#": "parameters (#) are", "[": "expressions ([ ]) are", "/": "block delete (/) is",
                "=": "parameter assignments are"}.get(ch)
        why = f"{what} not in the subset" if what else f"{ch!r} where a word (letter and number) belongs"
        raise GcodeError(self.f, n, bad + 1, ch, f"{why}; {_SUBSET}")

    def _strip_comments(self, n: int, raw: str) -> str:
        """The line with its comments blanked (columns kept); refuses an unclosed '('."""
        if "(" not in raw and ")" not in raw and ";" not in raw:
            return raw
        out = []
        i = 0
        while i < len(raw):
            c = raw[i]
            if c == ";":
                break
            if c == "(":
                j = raw.find(")", i)
                if j < 0:
                    raise GcodeError(self.f, n, i + 1, "(", "comment not closed on its line; close it with ')'")
                out.append(" " * (j - i + 1))
                i = j + 1
                continue
            if c == ")":
                raise GcodeError(self.f, n, i + 1, ")", "')' with no '(' before it")
            out.append(c)
            i += 1
        return "".join(out)

    def _block(self, n: int, words: list[_Word]) -> None:  # noqa: C901 (the rs274ngc order of execution)
        g: dict[str, tuple[float, _Word]] = {}
        m: dict[str, tuple[int, _Word]] = {}
        vals: dict[str, _Word] = {}
        for w in words:
            if w.letter == "G":
                code = round(w.value, 1)
                if code in _REFUSED_G:
                    raise self.err(n, w, f"{_REFUSED_G[code]} is not in the subset; {_SUBSET}")
                if code not in _GROUP:
                    raise self.err(n, w, f"G{_fmt(code)} is not in the subset (accepted: G0 G1 G2 G3 G4 G10 L2 "
                                         f"G17 G20 G21 G28 G40 G49 G53 G54-G59.3 G61 G61.1 G64 G80 G90 G91 "
                                         f"G90.1 G91.1 G92 G92.1 G94); {_SUBSET}")
                grp = _GROUP[code]
                if grp in g:
                    raise self.err(n, w, f"two G words of one modal group ({grp}) on a line "
                                         f"({g[grp][1].text} before it)")
                g[grp] = (code, w)
            elif w.letter == "M":
                code = w.value
                if code != int(code) or int(code) not in _M_GROUP:
                    raise self.err(n, w, f"M{_fmt(code)} is not in the subset (accepted: M0 M1 M2 M30, and "
                                         f"M3 M4 M5 M7 M8 M9 M62-M65 where gcode.words maps them); {_SUBSET}")
                grp = _M_GROUP[int(code)]
                if grp in m:
                    raise self.err(n, w, f"two M words of one modal group ({grp}) on a line")
                m[grp] = (int(code), w)
            elif w.letter in "ABCUVWTOHDEQ" and not (w.letter == "Q" and "path" in g):
                if w.letter == "Q":
                    vals[w.letter] = w  # checked below (G64 Q)
                    continue
                why = {"O": "subroutines and flow control (O words)", "T": "tool selection",
                       "H": "tool length offsets", "D": "cutter radius offsets",
                       "E": "the E word"}.get(w.letter, f"axis {w.letter} (this machine's axes: "
                                                         f"{' '.join(self.s.axes)})")
                raise self.err(n, w, f"{why} is not in the subset; {_SUBSET}")
            else:
                if w.letter in vals:
                    raise self.err(n, w, f"{w.letter} given twice on a line")
                vals[w.letter] = w
        used: set[str] = {"N"}
        # axis words this machine does not have
        for a in AXES:
            if a in vals and a not in self.s.axes:
                raise self.err(n, vals[a], f"axis {a} is not on this machine (axes: {' '.join(self.s.axes)}); "
                                           f"set gcode.axes in the config if it is")
        # 3 F
        if "F" in vals:
            w = vals["F"]
            if w.value < 0:
                raise self.err(n, w, "negative feed rate")
            self.f_word = w.value
            used.add("F")
        # 4 S
        if "S" in vals:
            w = vals["S"]
            if w.value < 0:
                raise self.err(n, w, "negative S")
            self._event(n, "S", w, w.value, False)
            used.add("S")
        # 7 spindle, 8 coolant, M62-M65
        for grp in ("spindle", "coolant", "dio"):
            if grp in m:
                code, w = m[grp]
                p = None
                if grp == "dio":
                    if "P" not in vals or vals["P"].value != int(vals["P"].value) or vals["P"].value < 0:
                        raise self.err(n, w, f"M{code} needs P, the output number (0, 1, ...)")
                    p = int(vals["P"].value)
                    used.add("P")
                value = 1.0 if code in (3, 4, 7, 8, 62, 64) else 0.0
                self._event(n, f"M{code}", w, value, code in (62, 63), p)
        # 10 dwell
        if "non_modal" in g and g["non_modal"][0] == 4:
            w = g["non_modal"][1]
            if "P" not in vals:
                raise self.err(n, w, "G4 needs P, the dwell in seconds")
            if vals["P"].value < 0:
                raise self.err(n, vals["P"], "negative dwell")
            self.segments.append(Dwell(vals["P"].value, n))
            used.add("P")
        # 11 plane (G17 only), 12 units
        if "units" in g:
            self.unit = INCH if g["units"][0] == 20 else MM
        # 13, 14 cancel words: nothing they cancel can be active (G41/42/43 are refused)
        # 15 coordinate system
        if "cs" in g:
            self.active = f"G{_fmt(g['cs'][0])}"
        # 16 path control
        if "path" in g:
            code, w = g["path"]
            if code == 64:
                if "P" in vals:
                    if vals["P"].value < 0:
                        raise self.err(n, vals["P"], "negative blend tolerance")
                    self.tol = vals["P"].value * self.unit
                    used.add("P")
                else:
                    self.tol = math.inf
                self.q = self.tol if math.isfinite(self.tol) else 0.0
                if "Q" in vals:
                    if vals["Q"].value < 0:
                        raise self.err(n, vals["Q"], "negative naive-CAM tolerance")
                    self.q = vals["Q"].value * self.unit
                    used.add("Q")
            else:
                self.tol = 0.0
                self.q = 0.0
        if "Q" in vals and "Q" not in used:
            raise self.err(n, vals["Q"], "Q is read only with G64 (its naive-CAM tolerance)")
        # 17 distance modes
        if "distance" in g:
            self.absolute = g["distance"][0] == 90
        if "arc_distance" in g:
            self.arc_absolute = g["arc_distance"][0] == 90.1
        # 19 G10 / G28 / G92 / G53
        machine_coords = False
        nonmodal_axes = False
        if "non_modal" in g:
            code, w = g["non_modal"]
            if code == 10:
                self._g10(n, w, vals)
                used |= {"L", "P", "X", "Y", "Z"}
                nonmodal_axes = True
            elif code == 92:
                given = [i for i, a in enumerate(AXES) if a in vals]
                if not given:
                    raise self.err(n, w, "G92 needs at least one axis word")
                for i in given:   # the current point reads the given value (absolute, as G90)
                    self.g92[i] = self.pos[i] - self.cs[self.active][i] - vals[AXES[i]].value * self.unit
                used |= set(AXES)
                nonmodal_axes = True
            elif code == 92.1:
                self.g92[:] = 0.0
            elif code == 28:
                given = [a for a in AXES if a in vals]
                via = self._targets(vals, self.offset())
                if given:
                    self._move(n, via, None)
                goal = self.pos.copy()
                for i, a in enumerate(AXES):
                    if not given or a in vals:
                        if a in self.s.axes:
                            goal[i] = self.ref[i]
                self._move(n, goal, None)
                used |= set(AXES)
                nonmodal_axes = True
            elif code == 53:
                machine_coords = True
        # 20 motion
        if "motion" in g:
            code, w = g["motion"]
            if code == 80:
                if any(a in vals for a in AXES):
                    raise self.err(n, w, "G80 with axis words on its line")
                self.motion = None
            else:
                self.motion = code
        has_axes = any(a in vals for a in AXES) and not nonmodal_axes
        if has_axes or ("motion" in g and g["motion"][0] in (2, 3)):
            wfirst = g["motion"][1] if "motion" in g else next(vals[a] for a in AXES if a in vals)
            if self.motion is None:
                raise self.err(n, wfirst, "axis words with no motion mode active (G0, G1, G2 or G3)")
            if machine_coords and self.motion not in (0, 1):
                raise self.err(n, g["non_modal"][1], "G53 works with G0 or G1 only")
            base = np.zeros(3) if machine_coords else self.offset()
            target = self._targets(vals, base)
            used |= set(AXES)
            if self.motion == 0:
                self._move(n, target, None)
            elif self.motion == 1:
                if self.feed is None:
                    raise self.err(n, wfirst, "G1 with no feed rate; give F (units per minute) first")
                self._move(n, target, self.feed)
            else:
                if self.feed is None:
                    raise self.err(n, wfirst, f"G{int(self.motion)} with no feed rate; give F first")
                self._arc(n, g.get("motion", (self.motion, wfirst))[1] or wfirst, target, vals)
                used |= {"I", "J", "K", "R", "P"}
        elif machine_coords:
            raise self.err(n, g["non_modal"][1], "G53 with no axis words")
        for letter, w in vals.items():
            if letter not in used:
                raise self.err(n, w, f"{letter} word with nothing on its line that reads it")
        # 21 stops
        if "stop" in m:
            code, w = m["stop"]
            if code in (0, 1):
                if code == 0 or self.s.optional_stop:
                    self.segments.append(Pause(code == 1, n))
            else:
                self.done = True

    def _event(self, n: int, word: str, w: _Word, value: float, sync: bool, p: int | None = None) -> None:
        key = word
        if key not in self.words_map:
            raise GcodeError(self.f, n, w.column, w.text,
                             f"{word} has no mapping: set gcode.words.{word} in the config to an output "
                             f"name or to 'ignore' (e.g. gcode: {{words: {{{word}: torch}}}})")
        out = self.words_map[key]
        if out == "ignore":
            self.warnings.append(f"{self.f}:{n}:{w.column}: {w.text} ignored (gcode.words.{word}: ignore)")
            self.segments.append(Event(word, None, value, sync, n, w.column, p))
            return
        if word == "M5":          # spindle off: the M3 and M4 outputs
            outs = {self.words_map.get("M3"), self.words_map.get("M4"), out} - {None, "ignore"}
            for o in sorted(outs):
                self.segments.append(Event(word, o, 0.0, False, n, w.column, p))
            return
        if word == "M9":
            outs = {self.words_map.get("M7"), self.words_map.get("M8"), out} - {None, "ignore"}
            for o in sorted(outs):
                self.segments.append(Event(word, o, 0.0, False, n, w.column, p))
            return
        self.segments.append(Event(word, out, value, sync, n, w.column, p))

    def _targets(self, vals: dict[str, _Word], base: np.ndarray) -> np.ndarray:
        """The machine position the axis words name (unnamed axes stay)."""
        t = self.pos.copy()
        for i, a in enumerate(AXES):
            if a in vals:
                v = vals[a].value * self.unit
                t[i] = self.pos[i] + v if not self.absolute else base[i] + v
        return t

    def _g10(self, n: int, w: _Word, vals: dict[str, _Word]) -> None:
        if "L" not in vals or vals["L"].value != 2:
            lw = vals.get("L")
            raise self.err(n, lw or w, "only G10 L2 (set a work offset) is in the subset; "
                                       "write G10 L2 P<1-9> X.. Y..")
        if "R" in vals:
            raise self.err(n, vals["R"], "rotated coordinate systems (G10 L2 R) are not in the subset")
        if "P" not in vals or vals["P"].value != int(vals["P"].value) or not 0 <= vals["P"].value <= 9:
            raise self.err(n, vals.get("P", w), "G10 L2 needs P 0-9 (0: the active system, 1: G54 ... 9: G59.3)")
        p = int(vals["P"].value)
        name = self.active if p == 0 else SYSTEMS[p - 1]
        for i, a in enumerate(AXES):
            if a in vals:
                self.cs[name][i] = vals[a].value * self.unit

    def _move(self, n: int, target: np.ndarray, feed: float | None) -> None:
        if target.tolist() == self.pos.tolist():
            return
        self.segments.append(Line(self.pos.copy(), target.copy(), feed, self.tol, n,
                                  0.0 if feed is None else self.q))
        self.pos = target

    def _arc(self, n: int, w: _Word, target: np.ndarray, vals: dict[str, _Word]) -> None:
        cw = self.motion == 2
        if "K" in vals:
            raise self.err(n, vals["K"], "K with G17 (arcs in XY take I and J)")
        turns = 1
        if "P" in vals:
            pv = vals["P"].value
            if pv != int(pv) or pv < 1:
                raise self.err(n, vals["P"], "P of an arc (turns) must be a whole number >= 1")
            turns = int(pv)
        start = self.pos
        if "R" in vals:
            if "I" in vals or "J" in vals:
                raise self.err(n, vals["R"], "R and I/J on one arc; give one of them")
            r = vals["R"].value * self.unit
            d = target[:2] - start[:2]
            chord = float(np.hypot(*d))
            if chord == 0.0:
                raise self.err(n, vals["R"], "a radius-format arc with its end at its start; a full "
                                             "circle needs I and J")
            if abs(r) < chord / 2 * (1 - 1e-9):
                raise self.err(n, vals["R"], f"radius {abs(r) / self.unit:g} is less than half the chord "
                                             f"({chord / 2 / self.unit:g})")
            h = math.sqrt(max(r * r - chord * chord / 4, 0.0))
            mid = (start[:2] + target[:2]) / 2
            perp = np.array([-d[1], d[0]]) / chord          # left of the chord
            # clockwise with r > 0: centre right of the chord; the long arc (r < 0) swaps sides
            side = -1.0 if cw else 1.0
            if r < 0:
                side = -side
            c2 = mid + side * h * perp
        else:
            if "I" not in vals and "J" not in vals:
                raise self.err(n, w, f"G{int(self.motion)} needs I and/or J (centre) or R (radius)")
            i = vals["I"].value * self.unit if "I" in vals else 0.0
            j = vals["J"].value * self.unit if "J" in vals else 0.0
            if self.arc_absolute:
                c2 = np.array([i + self.offset()[0], j + self.offset()[1]])
                if "I" not in vals:
                    c2[0] = start[0]
                if "J" not in vals:
                    c2[1] = start[1]
            else:
                c2 = start[:2] + np.array([i, j])
            r0 = float(np.hypot(*(start[:2] - c2)))
            r1 = float(np.hypot(*(target[:2] - c2)))
            if r0 == 0.0:
                raise self.err(n, vals.get("I") or vals.get("J"), "arc of zero radius")
            if abs(r1 - r0) > ARC_RADIUS_TOL_M and abs(r1 - r0) > ARC_RADIUS_TOL_REL * r0:
                raise self.err(n, vals.get("I") or vals.get("J"),
                               f"the radius to the end of the arc differs from the radius to its start by "
                               f"{abs(r1 - r0) / self.unit:g} (more than {ARC_RADIUS_TOL_M / self.unit:g} and "
                               f"0.1 %)")
        center = np.array([c2[0], c2[1], start[2]])
        self.segments.append(Arc(start.copy(), target.copy(), center, cw, turns - 1, self.feed, self.tol, n))
        self.pos = target


class ProgramReader:
    """A program read line by line with bounded memory: the segments come out in batches as
    they are read (:meth:`batches`), the reader keeps only the modal state (LinuxCNC's: position,
    units, distance mode, feed, tolerance, work offsets) between them, so that a program of any
    length can be checked and planned a window at a time (the daemon's planner process).

    Args: as :func:`parse` (``filename``, ``settings``, ``start``, ``offsets``).
    Raises:
        ValueError: an unknown work offset name in ``offsets``.
    """

    def __init__(self, filename: str, settings: GcodeSettings | None = None,
                 start: Sequence[float] | None = None,
                 offsets: Mapping[str, Sequence[float]] | None = None):
        self._r = _Reader(filename, settings or GcodeSettings(), start, offsets)
        self.lines_read = 0
        self._percent = 0
        self.ended = False

    def batches(self, lines, size: int = 1000):
        """The segments of ``lines`` (an iterable of source lines without or with their newline,
        e.g. an open text file), in lists of about ``size`` segments (the last one shorter).
        Raises :class:`GcodeError` (``file:line:column: word: why``) at the first word outside
        the subset; the batches yielded before it were valid."""
        r = self._r
        for raw in lines:
            if self.ended:
                break
            self.lines_read += 1
            k = self.lines_read
            raw = raw.rstrip("\r\n")
            s = raw.strip()
            if s.startswith("%"):
                if s[1:].strip() and not s[1:].lstrip().startswith(("(", ";")):
                    raise GcodeError(r.f, k, raw.index("%") + 2, s[1:].strip()[:1],
                                     "text after '%' on its line (a '%' line holds only '%' and a comment)")
                self._percent += 1
                if self._percent == 2:
                    self.ended = True
                continue
            r.line(k, raw)
            if r.done:
                self.ended = True
            if len(r.segments) >= size:
                out, r.segments = r.segments, []
                yield out
        if r.segments:
            out, r.segments = r.segments, []
            yield out

    def program(self, segments: list[Segment]) -> Program:
        """A :class:`Program` of ``segments`` with what the reader knows now: its start, the
        position after the lines read, the warnings and the work offsets."""
        r = self._r
        offsets_out = {k: v.copy() for k, v in r.cs.items()}
        offsets_out["G92"] = r.g92.copy()
        return Program(r.f, segments, r.start, r.pos.copy(), list(r.warnings), offsets_out)


def parse(text: str, filename: str, settings: GcodeSettings | None = None,
          start: Sequence[float] | None = None,
          offsets: Mapping[str, Sequence[float]] | None = None) -> Program:
    """Read a whole G-code program (the module docstring lists the subset; a program of any
    length: :class:`ProgramReader`).

    text: the program. filename: named in errors. settings: the ``gcode:`` config
    (:class:`GcodeSettings`; None: no machine words mapped, G28 to 0, axes X Y Z). start: the machine
    position before the program, X Y Z [m] (None: 0). offsets: work offsets before the program
    (``"G54"`` ... → X Y Z [m], the origin of that system in machine coordinates; None: all 0).

    Returns a :class:`Program` (machine coordinates [m], path speeds [m/s]). Raises
    :class:`GcodeError` (``file:line:column: word: why``) at the first word outside the subset,
    and nothing of the program is returned.
    """
    reader = ProgramReader(filename, settings, start, offsets)
    segments: list[Segment] = []
    for batch in reader.batches(text.splitlines(), size=1 << 62):
        segments.extend(batch)
    return reader.program(segments)
