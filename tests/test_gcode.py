"""The G-code reader (motorctl.motion.gcode): LinuxCNC's semantics for the accepted subset, the
CAM words mapped by configuration, and refusals with file:line:column."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorctl.motion import Arc, Dwell, Event, GcodeError, GcodeSettings, Line, Pause, parse
from conftest import REPO, examples

from motorctl.motion import gcode

XY = GcodeSettings(axes=["X", "Y"])
CAM = GcodeSettings(axes=["X", "Y"], words={"M03": "torch", "M5": "torch", "S": "ignore", "M62": "dout"},
                    reference_point_m={"X": 0.001, "Y": 0.002})


def _err(text, settings=XY):
    with pytest.raises(GcodeError) as e:
        parse(text, "p.ngc", settings)
    return e.value


def test_motion_units_modes_and_lexing():
    p = parse("%\n(header) N10 G21 G90 G64 P0.01\nn20 g0 x10 Y20 ; rapid\nN30 G1 X.5 Y-0.500 F6000\n"
              "G20 G91 G1 X1 ( an inch )\nM2\nG1 X99\n%\n", "p.ngc", XY)
    a, b, c = p.segments
    assert isinstance(a, Line) and a.feed is None and a.line == 3
    np.testing.assert_allclose(a.end[:2], [0.010, 0.020])
    assert b.feed == pytest.approx(0.1) and b.tolerance == pytest.approx(1e-5)
    np.testing.assert_allclose(b.end[:2], [0.0005, -0.0005])
    np.testing.assert_allclose(c.end[:2], [0.0005 + 0.0254, -0.0005])     # G91, inches
    assert c.feed == pytest.approx(6000 * 0.0254 / 60)                  # F stays 6000, now in/min
    np.testing.assert_allclose(p.end[:2], c.end[:2])                    # nothing after M2


def test_arcs_centre_and_radius_formats():
    p = parse("G21 G90 G1 X10 Y0 F600\nG2 X0 Y-10 I-10 J0\nG3 X10 Y0 R10\nG2 X-10 Y0 R-10\n"
              "G3 X-10 Y0 I10 J0\n", "p.ngc", XY)
    _, q, h, big, full = p.segments
    assert q.cw and q.sweep == pytest.approx(-math.pi / 2)
    np.testing.assert_allclose(q.center[:2], [0, 0], atol=1e-12)
    assert not h.cw and h.sweep == pytest.approx(math.pi / 2) and h.radius == pytest.approx(0.01)
    np.testing.assert_allclose(h.center[:2], [0, 0], atol=1e-12)
    assert big.cw and big.sweep == pytest.approx(-math.pi)  # R<0: the long way (here exactly 180 deg)
    assert full.sweep == pytest.approx(2 * math.pi) and full.length == pytest.approx(2 * math.pi * 0.01)
    r_long = parse("G21 G90 G1 X10 Y0 F600\nG2 X0 Y10 R-10\n", "p.ngc", XY).segments[1]
    assert r_long.sweep == pytest.approx(-1.5 * math.pi)   # the 270-degree arc


def test_cam_words_offsets_and_pauses():
    text = ("%\nG21 G90 G40 G49 G80 G54\nG10 L2 P2 X5 Y5\nG55 G0 X0 Y0\nM03 S1000\nG4 P0.5\n"
            "G92 X1\nG1 X2 F600\nG92.1\nM62 P3\nG1 X3\nM00\nM01\nM05\nG28\nM30\n%\n")
    p = parse(text, "cam.ngc", CAM)
    kinds = [type(s).__name__ for s in p.segments]
    assert kinds == ["Line", "Event", "Event", "Dwell", "Line", "Event", "Line", "Pause", "Event", "Line"]
    seg = p.segments
    np.testing.assert_allclose(seg[0].end[:2], [0.005, 0.005])          # G55 after G10 L2 P2
    assert seg[1].output is None and seg[1].word == "S" and p.warnings  # S ignored, with a warning
    assert (seg[2].word, seg[2].output, seg[2].value, seg[2].synchronized) == ("M3", "torch", 1.0, False)
    assert seg[3] == Dwell(0.5, 6)
    np.testing.assert_allclose(seg[4].end[:2], [0.006, 0.005])          # G92 X1 here: X2 is 1 mm on
    assert (seg[5].word, seg[5].output, seg[5].p, seg[5].synchronized) == ("M62", "dout", 3, True)
    np.testing.assert_allclose(seg[6].end[:2], [0.008, 0.005])          # G92.1: back to G55
    assert seg[7] == Pause(False, 12)                                   # M01 passes: optional stop off
    assert (seg[8].word, seg[8].value) == ("M5", 0.0)
    np.testing.assert_allclose(seg[9].end[:2], [0.001, 0.002])          # G28: the reference point
    p2 = parse(text, "cam.ngc", CAM.model_copy(update={"optional_stop": True}))
    assert [s for s in p2.segments if isinstance(s, Pause)] == [Pause(False, 12), Pause(True, 13)]


def test_start_and_offsets_arguments():
    p = parse("G21 G91 G1 X1 F60\nG90 G54 G1 X1\n", "p.ngc", XY, start=[0.1, 0.2, 0.0],
              offsets={"G54": [0.05, 0, 0]})
    np.testing.assert_allclose(p.segments[0].start[:2], [0.1, 0.2])
    np.testing.assert_allclose(p.segments[0].end[:2], [0.101, 0.2])
    np.testing.assert_allclose(p.segments[1].end[:2], [0.051, 0.2])


@pytest.mark.parametrize("text, where, word, says", [
    ("G21\nG18\n", (2, 1), "G18", "XZ plane"),
    ("G21 M03\n", (1, 5), "M03", "gcode.words.M3"),
    ("G1 X1 F100\nT1 M6\n", (2, 1), "T1", "tool selection"),
    ("G1 X#1\n", (1, 5), "#", "parameters"),
    ("G1 X[1+2]\n", (1, 5), "[", "expressions"),
    ("G1 X1 (no end\n", (1, 7), "(", "not closed"),
    ("G21 G90\nG1 X1\n", (2, 1), "G1", "no feed rate"),
    ("G0 X1 A2\n", (1, 7), "A2", "axis A"),
    ("G0 X1 Z1\n", (1, 7), "Z1", "not on this machine"),
    ("G0 G1 X1\n", (1, 4), "G1", "modal group"),
    ("G1 X1 I2 F100\n", (1, 7), "I2", "nothing on its line that reads it"),
    ("G1 X1 X2 F100\n", (1, 7), "X2", "twice"),
    ("G2 X1 Y1 F100\n", (1, 1), "G2", "needs I and/or J"),
    ("G2 X10 Y0 I3 F100\n", (1, 11), "I3", "radius to the end"),
    ("G43 H1\n", (1, 1), "G43", "tool length"),
    ("G81 X1\n", (1, 1), "G81", "not in the subset"),
    ("M98 P1\n", (1, 1), "M98", "not in the subset"),
    ("O100 sub\n", (1, 1), "O100", "subroutines"),
    ("G10 L20 P1 X0\n", (1, 5), "L20", "G10 L2"),
    ("G4\n", (1, 1), "G4", "needs P"),
    ("M62\n", (1, 1), "M62", "needs P"),
])
def test_refusals_name_line_column_word_and_remedy(text, where, word, says):
    s = GcodeSettings(axes=["X", "Y"], words={"M62": "dout"}) if "M62" in text else XY
    e = _err(text, s)
    assert (e.line, e.column) == where
    assert e.word.upper() == word.upper()
    assert says in str(e)
    assert str(e).startswith(f"p.ngc:{where[0]}:{where[1]}: ")
    assert "\n" not in str(e)


def test_settings_refuse_an_unknown_machine_word_and_an_ignored_off_word():
    with pytest.raises(ValueError, match="M6"):
        GcodeSettings(words={"M6": "x"})
    with pytest.raises(ValueError, match="gcode.words.M5: 'ignore' would leave the output of M3"):
        GcodeSettings(words={"M03": "torch", "M05": "ignore"})
    GcodeSettings(words={"M3": "ignore", "M5": "ignore"})


def test_the_shipped_programs_parse():
    sq = parse((REPO / "configs" / "square_and_circle.ngc").read_text(), "square_and_circle.ngc", XY)
    np.testing.assert_allclose(sq.end[:2], [0.010, 0.020])
    arcs = [s for s in sq.segments if isinstance(s, Arc)]
    assert len(arcs) == 1 and arcs[0].radius == pytest.approx(0.020)
    cam = parse((REPO / "configs" / "cam_sample.ngc").read_text(), "cam_sample.ngc", CAM)
    assert len(cam.moves) >= 300
    assert {s.word for s in cam.segments if isinstance(s, Event)} >= {"M3", "M5", "S"}


def test_machine_coordinates_absolute_centres_turns_and_helix():
    p = parse("G21 G90 G10 L2 P1 X100\nG54 G0 X0\nG53 G0 X5\nG0 X10 Y0\nG90.1 G3 X10 Y0 I110 J0 P2 F600\n"
              "G91.1 G2 X0 Y10 Z5 I0 J10\n", "p.ngc", GcodeSettings())
    a, b, c, two_turns, helix = p.segments
    assert a.end[0] == pytest.approx(0.1) and b.end[0] == pytest.approx(0.005)   # G53: machine X5
    np.testing.assert_allclose(two_turns.center[:2], [0.210, 0.0])             # G90.1: I in G54, absolute
    assert two_turns.turns == 1 and two_turns.sweep == pytest.approx(4 * np.pi)
    assert helix.length == pytest.approx(np.hypot(0.5 * np.pi * 0.01, 0.005))


_FAST_TOKENS = ["G0", "G1", "G01", "G00", "g1", "G1.0", "G2", "N10", "X", "Y", "Z", "F", "x", "f", "M3"]
_FAST_NUMBERS = ["10", "-5.5", ".5", "5.", "+3", "0", "-0", "1e3", "12.345", "", "1 0"]
_FAST_LINE = st.lists(st.tuples(st.sampled_from(_FAST_TOKENS), st.sampled_from(_FAST_NUMBERS)).map(
    lambda tn: tn[0] + (tn[1] if tn[0][0] in "XYZFxyzf" else "")), max_size=5).flatmap(
    lambda words: st.sampled_from([" ", "", "\t"]).map(lambda sep: sep.join(words)))


@settings(max_examples=examples(300), deadline=None)
@given(lines=st.lists(_FAST_LINE, min_size=1, max_size=6))
def test_the_fast_path_reads_as_the_general_path(lines):
    """Lines of straight moves take the reader's fast path (gcode._SIMPLE); any line, taken
    there or not, gives the same segments, modal state and errors as the general path alone."""
    def read(fast: bool):
        r = gcode._Reader("t.ngc", GcodeSettings(axes=["X", "Y"]), None, None)
        if not fast:
            r._simple = lambda n, raw: False
        try:
            for k, ln in enumerate(["G21 G90", "F600", *lines], 1):
                r.line(k, ln)
        except GcodeError as exc:
            return ("refused", str(exc))
        return ([(s.start.tolist(), s.end.tolist(), s.feed, s.tolerance, s.line) for s in r.segments],
                r.f_word, r.motion)
    assert read(True) == read(False)


def test_g64_q_is_the_naive_cam_tolerance_of_feed_lines():
    """LinuxCNC's G64 P Q: Q [program units] is each straight feed move's naive-CAM tolerance
    (Line.naive_cam, metres), P when Q is not given, 0 for rapids and under G61; a negative Q
    is refused by line and column."""
    prog = parse("G21 G64 P0.01\nG1 X1 F600\nG0 X2\nG64 P0.02 Q0.005\nG1 X3\nG20 G64 P0.001 Q0.0004\nG1 X4\n"
                 "G61\nG1 X5\n", "q.ngc", GcodeSettings())
    assert [m.naive_cam for m in prog.moves] == pytest.approx([1e-5, 0.0, 5e-6, 0.0004 * 25.4e-3, 0.0])
    with pytest.raises(GcodeError, match=r"q.ngc:1:.*Q-0.1.*negative naive-CAM tolerance"):
        parse("G64 P0.01 Q-0.1\n", "q.ngc", GcodeSettings())


def test_the_contour_benchmark_programs_parse():
    """configs/cut_path.ngc and configs/dxf2gcode_lid_wing.ngc (benchmarks/bench_contour.py):
    hundreds of short moves, read whole, each with the G64 P of its header."""
    for name, moves in (("cut_path.ngc", 300), ("dxf2gcode_lid_wing.ngc", 200)):
        prog = parse((REPO / "configs" / name).read_text(), name, CAM)
        feeds = [m for m in prog.moves if m.feed is not None]
        assert len(prog.moves) >= moves and {m.tolerance for m in feeds} == {1e-5}
