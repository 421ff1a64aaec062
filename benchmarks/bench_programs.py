"""Real programs on a busy PC: the daemon on configs/gantry.yaml (simulated gantry, wall clock),
X and Y in command mode, CPU-bound processes at normal priority beside it, and the programs a
CAM system sends, through the user's path (the socket, ``motorctl.client``; ``status`` through the
CLI as a child process).

    python benchmarks/bench_programs.py                      # 4 hogs, 5 runs of each program
    python benchmarks/bench_programs.py --repeat 1 --hogs 0  # a quick look at rest
    python benchmarks/bench_programs.py --million            # also the 1 000 000-line program
    python benchmarks/bench_programs.py --contour --repeat 1 # benchmarks/bench_contour.py's five programs
    python benchmarks/bench_programs.py --real               # the real CAM programs and the cut path

Prints, per program and run: faults, underruns, the end point's distance from the program's end
[um], rows lost, the run's time; then the loop's turnaround p99.9 while streaming against at rest
in command mode (the run log's ``turnaround_ns``, same run), ``status`` answer times idle and
beside the hogs, the override alternating 0.5 / 1.5 every 2 s through the CAM program, and with
``--million`` the whole-program check's time (a violation on the last line: refused, nothing
moved), the time to the first motion of the valid million-line program and the daemon's RSS
growth while it runs (all its processes: loop, I/O, planner).

The programs are made here: ``cam_program`` (plasma parts: rapid to a pierce point, M3 S, a 1-3 mm
lead-in arc, the contour of lines and arcs, a lead-out, M5; ~700 segments), ``steps_program``
(0.1 mm steps at F6000 in rows), ``million_program`` (1 000 000 lines of 0.05 mm steps). With
``--contour`` instead: the five programs benchmarks/bench_contour.py times against TOPP-RA (the
ISO 230-4 circle R 50 mm at 50 and 100 mm/s, configs/cut_path.ngc, configs/dxf2gcode_lid_wing.ngc,
configs/plate_0932.ngc). With ``--real``: configs/plate_0932.ngc (a plasma post's program),
configs/dxf2gcode_lid_wing.ngc (DXF2GCODE output) and configs/cut_path.ngc, and the override run
through plate_0932.ngc. The verdict counts the override run too.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from motorctl.client import Client, DaemonUnreachable  # noqa: E402


def _spin() -> None:  # pragma: no cover  (a background load; killed by the parent)
    x = 0
    while True:
        x += 1


# ------------------------------------------------------------------------------------ programs
def cam_program(parts: int = 20, seed: int = 1) -> tuple[str, tuple[float, float]]:
    """A plasma post's program of ``parts`` parts (circles of 8 arcs, rounded rectangles whose
    sides come in 3 mm pieces as a post writes polylines), each pierced after a rapid with M3 S..,
    entered by a lead-in arc of 1-3 mm radius and left by a lead-out line before M5, inside
    X 20..380, Y 20..380 mm. Returns (text, end point (X, Y) [mm])."""
    rng = np.random.default_rng(seed)
    out = ["%", "(bench_programs cam_program)", "G21 G90 G64 P0.01", "G17 G40 G49 G80"]
    cols = int(math.ceil(math.sqrt(parts)))
    pitch = 360.0 / cols
    for k in range(parts):
        cx, cy = 20 + pitch * (k % cols + 0.5), 20 + pitch * (k // cols + 0.5)
        size = pitch * 0.35
        r_in = float(rng.uniform(1.0, 3.0))
        sx, sy = cx - size, cy                   # the contour's start
        out.append(f"N{10 * k + 10} G0 X{sx - r_in:.3f} Y{sy - r_in:.3f}")
        out.append("M3 S4000")
        out.append(f"G3 X{sx:.3f} Y{sy:.3f} I0 J{r_in:.3f} F4000")      # lead-in, a quarter arc
        if k % 2 == 0:                           # a circle: 8 arcs of 45 degrees
            for q in range(8):
                a = math.pi + (q + 1) * math.pi / 4
                out.append(f"G3 X{cx + size * math.cos(a):.3f} Y{cy + size * math.sin(a):.3f} R{size:.3f}")
        else:                                    # a rounded rectangle, clockwise
            rc = 0.2 * size
            corners = [((cx - size, cy + size - rc), (cx - size + rc, cy + size)),
                       ((cx + size - rc, cy + size), (cx + size, cy + size - rc)),
                       ((cx + size, cy - size + rc), (cx + size - rc, cy - size)),
                       ((cx - size + rc, cy - size), (cx - size, cy - size + rc))]
            px, py = sx, sy
            for (ax, ay), (bx, by) in corners:
                n = max(1, int(math.hypot(ax - px, ay - py) / 3.0))
                for j in range(1, n + 1):
                    out.append(f"G1 X{px + (ax - px) * j / n:.3f} Y{py + (ay - py) * j / n:.3f}")
                out.append(f"G2 X{bx:.3f} Y{by:.3f} R{rc:.3f}")
                px, py = bx, by
            n = max(1, int(abs(sy - py) / 3.0))
            for j in range(1, n + 1):
                out.append(f"G1 X{sx:.3f} Y{py + (sy - py) * j / n:.3f}")
        out.append(f"G1 X{sx + 1.5:.3f} Y{sy + 1.5:.3f}")                # lead-out
        out.append("M5")
    out += ["G0 X10 Y10", "M2", "%"]
    return "\n".join(out) + "\n", (10.0, 10.0)


def steps_program(n: int = 10_000, step_mm: float = 0.1, row: int = 500) -> tuple[str, tuple[float, float]]:
    """n straight 0.1 mm steps at F6000, in rows of ``row`` steps 2 mm apart (zig-zag)."""
    out = ["G21 G90 G64 P0.01", "G0 X50 Y50", "F6000"]
    x, y = 50.0, 50.0
    d = 1.0
    for k in range(n):
        if k and k % row == 0:
            y += 2.0
            d = -d
        else:
            x += d * step_mm
        out.append(f"G1 X{x:.3f} Y{y:.3f}")
    out.append("M2")
    return "\n".join(out) + "\n", (x, y)


def million_program(path: Path, n: int = 1_000_000, bad_last: bool = False) -> None:
    """n lines of 0.05 mm steps at F6000 in rows of 4000 (X 50..250 mm); with ``bad_last`` the
    last line leaves the soft limits (X 500 mm)."""
    with open(path, "w") as fh:
        fh.write("G21 G90 G64 P0.01\nG0 X50 Y50\nF6000\n")
        x, y, d = 50.0, 50.0, 1.0
        for k in range(n - 4):
            if k and k % 4000 == 0:
                y += 0.05
                d = -d
            else:
                x += d * 0.05
            fh.write(f"G1 X{x:.3f} Y{y:.4f}\n")
        fh.write("G1 X500\n" if bad_last else "M2\n")


#: the real CAM programs and the cut path (``--real``)
REAL = ("plate_0932.ngc", "dxf2gcode_lid_wing.ngc", "cut_path.ngc")


def contour_programs(circles: bool = True, names=("cut_path.ngc", "dxf2gcode_lid_wing.ngc", "plate_0932.ngc")
                     ) -> list[tuple[str, tuple[float, float], str]]:
    """benchmarks/bench_contour.py's programs (the circles when ``circles``, then ``names`` of
    configs/): (text, end point (X, Y) [mm], name) each."""
    from motorctl.motion import GcodeSettings, parse
    from motorctl.motion.circle import circle_program
    settings = GcodeSettings(axes=["X", "Y"], words={"M3": "torch", "M5": "torch", "S": "ignore"})
    out = []
    for feed in (0.05, 0.1) if circles else ():
        text, _ = circle_program(0.05, feed, center=(0.2, 0.2))
        out.append((text, f"circle_F{feed * 6e4:.0f}"))
    for name in names:
        out.append(((REPO / "configs" / name).read_text(), name))
    return [(text, tuple(parse(text, name, settings).end[:2] * 1e3), name) for text, name in out]


# ------------------------------------------------------------------------------------ the daemon
class Daemon:
    def __init__(self, tmp: Path, realtime: str):
        d = yaml.safe_load((REPO / "configs" / "gantry.yaml").read_text())
        d["daemon"].update(socket=str(tmp / "motorctl.sock"), log_dir=str(tmp / "logs"))
        d["loop"]["realtime"]["policy"] = realtime
        d["gcode"] = {"words": {"M3": "torch", "M5": "torch", "S": "ignore"}}
        self.cfg = tmp / "gantry.yaml"
        self.cfg.write_text(yaml.safe_dump(d))
        self.sock = str(tmp / "motorctl.sock")
        self.err = open(tmp / "daemon.err", "w")
        self.proc = subprocess.Popen([sys.executable, "-m", "motorctl", "daemon", str(self.cfg)],
                                     stdout=self.err, stderr=self.err, cwd=REPO)
        self.c = Client(self.sock, timeout_s=10.0)
        try:
            try:
                self.c.wait_started(300, alive=lambda: self.proc.poll() is None)
            except DaemonUnreachable as exc:
                raise SystemExit(f"{exc}; see {tmp / 'daemon.err'}") from None
            for a in ("X", "Y"):
                self.c.start(a, mode="command")
        except BaseException:
            self.stop()                  # a daemon that did not come up is not left running
            raise
        time.sleep(0.5)

    def pids(self) -> list[int]:
        out = subprocess.run(["pgrep", "-P", str(self.proc.pid)], capture_output=True, text=True).stdout
        kids = [int(p) for p in out.split()]
        more = []
        for k in kids:
            o = subprocess.run(["pgrep", "-P", str(k)], capture_output=True, text=True).stdout
            more += [int(p) for p in o.split()]
        return [self.proc.pid] + kids + more

    def rss_mb(self) -> float:
        tot = 0
        for p in self.pids():
            try:
                for line in open(f"/proc/{p}/status"):
                    if line.startswith("VmRSS:"):
                        tot += int(line.split()[1])
            except OSError:
                pass
        return tot / 1024

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def run_program(dm: Daemon, text: str, end_mm, name: str, override_flip: bool = False) -> dict:
    c = dm.c
    st0 = c.status()
    u0 = st0["motion"]["underruns"]
    lost0 = st0["log"]["lost_rows"]
    t0 = time.monotonic()
    ans = c.gcode(text, name)
    t_answer = time.monotonic() - t0
    stop = threading.Event()
    flips = 0

    def flip():
        nonlocal flips
        v = 0.5
        while not stop.wait(2.0):
            c.override(v)
            flips += 1
            v = 2.0 - v
    th = threading.Thread(target=flip, daemon=True) if override_flip else None
    if th:
        th.start()
    while True:
        st = c.status()
        mo = st["motion"]
        if mo["idle"] or any(a["fault"] for a in st["axes"].values()) or mo["stopped_because"].startswith("paused: underrun"):
            break
        time.sleep(0.1)
    stop.set()
    if th:
        th.join()
        c.override(1.0)
    time.sleep(0.3)
    st = c.status()
    y = np.array([st["axes"][a]["y_m"] for a in ("X", "Y")])
    if not st["motion"]["idle"]:             # paused (an underrun): dropped before the next run
        c.abort()
        while not c.status()["motion"]["idle"]:
            time.sleep(0.1)
    err = float(np.max(np.abs(y - np.array(end_mm) * 1e-3))) * 1e6
    return {"name": name, "faults": [f"{a}: {s['fault']}" for a, s in st["axes"].items() if s["fault"]],
            "underruns": st["motion"]["underruns"] - u0, "end_um": err, "answer_s": t_answer,
            "run_s": time.monotonic() - t0, "lost_rows": st["log"]["lost_rows"] - lost0,
            "why": st["motion"]["stopped_because"], "segments": ans.get("segments"), "flips": flips}


def status_times(sock: str, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-m", "motorctl", "--socket", sock, "status"], capture_output=True,
                       check=True)
        out.append(time.monotonic() - t0)
    return out


def turnaround(run_path: str) -> tuple[float, float, int, int]:
    """p99.9 of the turnaround [us] on rows where an axis streams a moving setpoint, and on rows
    in command mode at rest (both axes in command mode, every setpoint velocity 0)."""
    from motorctl.loop.cycle import STREAM
    from motorctl.recorder.segments import read_run
    log = read_run(run_path)
    ta = log.col("turnaround_ns") / 1e3
    cmd = np.ones(len(ta), bool)
    moving = np.zeros(len(ta), bool)
    for a in ("X", "Y"):
        cmd &= log.col(f"{a}.mode") == STREAM
        moving |= log.col(f"{a}.xd_dot") != 0
    mv, rest = ta[cmd & moving], ta[cmd & ~moving]
    return float(np.percentile(mv, 99.9)), float(np.percentile(rest, 99.9)), int(mv.size), int(rest.size)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hogs", type=int, default=4, help="CPU-bound processes beside the daemon (default 4)")
    ap.add_argument("--repeat", type=int, default=5, help="runs of each program (default 5)")
    ap.add_argument("--million", action="store_true", help="also the 1 000 000-line program")
    ap.add_argument("--realtime", default="best_effort", choices=("off", "best_effort", "required"))
    ap.add_argument("--contour", action="store_true",
                    help="run benchmarks/bench_contour.py's five programs instead (no override run)")
    ap.add_argument("--real", action="store_true",
                    help="run the real CAM programs and the cut path instead (configs/plate_0932.ngc, "
                         "dxf2gcode_lid_wing.ngc, cut_path.ngc), the override run on plate_0932.ngc")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_programs-"))
    cam, cam_end = cam_program()
    steps, steps_end = steps_program()
    print(f"cam_program: {cam.count(chr(10))} lines, {len(cam)} bytes; steps_program: "
          f"{steps.count(chr(10))} lines, {len(steps)} bytes; host load {os.getloadavg()[0]:.1f}")
    dm = Daemon(tmp, args.realtime)
    hogs: list = []
    try:
        idle = status_times(dm.sock, 10)
        for _ in range(args.hogs):
            p = mp.Process(target=_spin, daemon=True)
            p.start()
            hogs.append(p)
        time.sleep(1.0)
        busy = status_times(dm.sock, 10)
        rows = []
        for k in range(args.repeat):
            progs = (contour_programs() if args.contour else contour_programs(False, REAL) if args.real else
                     ((cam, cam_end, "cam_program"), (steps, steps_end, "steps_program")))
            for text, end, name in progs:
                r = run_program(dm, text, end, name)
                rows.append(r)
                print(f"  {name:14s} run {k + 1}: {r['segments']} segments, faults {r['faults'] or 0}, underruns "
                      f"{r['underruns']}, end {r['end_um']:.2f} um, rows lost {r['lost_rows']}, answered in "
                      f"{r['answer_s']:.2f} s, {r['run_s']:.1f} s in all{'; ' + r['why'] if r['why'] else ''}",
                      flush=True)
        flip = contour_programs(False, REAL[:1])[0] if args.real else (cam, cam_end, "cam_program")
        r = None if args.contour else run_program(dm, *flip, override_flip=True)
        if r:
            rows.append(r)
            print(f"  override 0.5/1.5 every 2 s through {flip[2]} ({r['flips']} changes): faults "
                  f"{r['faults'] or 0}, underruns {r['underruns']}, end {r['end_um']:.2f} um, rows lost "
                  f"{r['lost_rows']}", flush=True)
        if args.million:
            bad, good = tmp / "million_bad.ngc", tmp / "million.ngc"
            million_program(bad, bad_last=True)
            million_program(good)
            y0 = [dm.c.status()["axes"][a]["y_m"] for a in ("X", "Y")]
            t0 = time.monotonic()
            try:
                dm.c.gcode(bad.read_text(), str(bad))
                print("  million_bad: NOT refused")
            except Exception as exc:  # noqa: BLE001 - the refusal is the figure
                y1 = [dm.c.status()["axes"][a]["y_m"] for a in ("X", "Y")]
                print(f"  million-line program, violation on its last line: refused in "
                      f"{time.monotonic() - t0:.2f} s ({str(exc)[:90]}...); moved "
                      f"{max(abs(a - b) for a, b in zip(y0, y1)) * 1e6:.2f} um", flush=True)
            rss0 = dm.rss_mb()
            text = good.read_text()
            t0 = time.monotonic()
            ans = dm.c.gcode(text, str(good))
            t_ans = time.monotonic() - t0
            del text
            peak = rss0
            t1 = time.monotonic()
            moved_at = None
            while time.monotonic() - t1 < 30:
                st = dm.c.status()
                if moved_at is None and st["motion"]["feed_m_s"] > 0:
                    moved_at = time.monotonic() - t0
                peak = max(peak, dm.rss_mb())
                time.sleep(0.5)
            dm.c.abort()
            print(f"  million-line program: checked and first window planned in {t_ans:.2f} s "
                  f"({ans['segments']} segments), moving at {moved_at or float('nan'):.2f} s; daemon RSS "
                  f"{rss0:.0f} MB -> peak {peak:.0f} MB over 30 s of motion (+{peak - rss0:.0f} MB)", flush=True)
            time.sleep(2.0)
        mv, rest, n_mv, n_rest = turnaround(dm.c.status()["log"]["run"])
        for p in hogs:
            p.terminate()
        print(f"turnaround p99.9: streaming {mv:.1f} us ({n_mv} rows), at rest in command mode {rest:.1f} us "
              f"({n_rest} rows), ratio {mv / rest:.2f}")
        print(f"status (the CLI, a child process): idle median {statistics.median(idle):.3f} s max "
              f"{max(idle):.3f} s; beside {args.hogs} hogs median {statistics.median(busy):.3f} s max "
              f"{max(busy):.3f} s")
        ok = all(not r["faults"] and r["underruns"] == 0 and r["end_um"] <= 5.0 for r in rows)
        print(f"{sum(not r['faults'] and r['underruns'] == 0 and r['end_um'] <= 5.0 for r in rows)} of "
              f"{len(rows)} runs to their end with 0 faults, 0 underruns, end within 5 um")
        return 0 if ok else 1
    finally:
        for p in hogs:
            p.terminate()
        dm.stop()
        print(f"logs: {tmp}")


if __name__ == "__main__":
    sys.exit(main())
