"""What ``motorctl identify`` names for effects that no effect family models (and a few that
one does), on records made by two independent simulations written here (numpy only: not
motorctl's simulator, not its effect families): the right name, "ambiguous: A or B",
"unexplained" (the residual verdict's warning, nothing wrongly named), or a wrong name.
Simulation A (the default) is a PID loop on a 15 kg axis; simulation B (``--sim b``, below) a
cascade on a 6 kg axis with another friction law, program and set of effects: the records a
user brings come from machines we have never seen, and one simulation is one sample of them.

Run (A: 13 cases x 3 seeds, 40-90 s on 2 shared cores, a record 0.2-0.7 s to simulate and
1.5-5 s to identify; B: 12 cases x 3 seeds, about 80 s, a record 0.4-1.8 s to simulate and
1.5-6.5 s to identify):

    python benchmarks/ident_unmodelled.py                       # A: all cases, seeds 1-3, 2 jobs
    python benchmarks/ident_unmodelled.py --case backlash150 --seeds 1-5 --keep /tmp/iu
    python benchmarks/ident_unmodelled.py --seeds 4,7 --jobs 1
    python benchmarks/ident_unmodelled.py --sim b --seeds 1-3   # B: all its cases

``--sim`` a (default) or b; ``--seeds`` N, N-M or a comma list; ``--case`` repeatable (default
all of the simulation's cases); ``--jobs`` processes (default 2); ``--keep DIR`` keeps each CSV
and identify's JSON beside it (``<case>_seed<N>.csv``, ``.json``; B's ``b_<case>_seed<N>.csv``);
``--zoh-delay 0.5`` passes the loop's true timing (u written after y is read and held
over the sample) to identify, a diagnostic: by default it is not given, as a user with a CSV
would not, and identify looks for the hold in the data. Prints one line per record, then a
Markdown table (and the stderr of each failed identify). Exit 1 when identify failed on a record
(exit code != 0). The ``motorctl``
measured is the one ``python -m motorctl`` imports from the working directory (the repository's,
run from its root); to measure a snapshot, export it (``git archive HEAD motorctl
motorctl_drivers motorctl_emulators | tar -x -C DIR``) and run from outside the repository with
``PYTHONPATH=DIR``.

**The user's path.** Each record is a CSV ``t,y,u`` [s, m, V] (no ``yd``), identified by the CLI
in a subprocess: ``sys.executable -m motorctl identify REC.csv --gain 40 --json`` (the force
gain K0 in N/V, as a user gives it; identify looks for the zero-order hold in the data). Records
are 12 s at 1 kHz (identify needs >= 1 s and 200 samples, uniform time, motion; its held-out
test cuts 0.25 s blocks; the program repeats 7.5 times, the "at least 3 periods" of its
program-harmonic test).

**The plant and loop of A** (:func:`simulate`; SI units). A single-axis linear motor: carriage mass
M = 15 kg, force F = K0 K(x) u with K0 = 40 N/V (K = 1 but in the end-effect cases), viscous
friction B = 25 N s/m and Coulomb friction Fc = 12 N in Karnopp's form (the carriage is held
while |F| <= Fc; D. Karnopp, "Computer simulation of stick-slip friction in mechanical dynamic
systems", ASME J. Dyn. Syst. Meas. Control 107(1), 1985), a white force noise of 0.2 N RMS held
over each sample, integrated (semi-implicit Euler) at 10 kHz with u held over each 1 ms sample.
The encoder reading is rounded to 1 um counts. The loop at 1 kHz: PID on the reading (12000 V/m,
2e5 V/(m s), 90 V s/m on the error's difference through a 300 Hz first-order low-pass) plus
feedforward of the reference's acceleration and speed at 95 % of M and B; u clipped at
+-10 V. The program: a cycloidal move 0.05 -> 0.35 m in 0.6 s (peak 1 m/s, 5.2 m/s^2), a 0.2 s
dwell, back, a 0.2 s dwell: period T = 1.6 s. Tracking error about 10 um RMS, |u| <= 2.7 V.

**The cases of A** (each at the size given, some at a second size; seeded ``numpy.random.default_rng``
per seed: the noises only, so a record is the same on every run):

1. ``clean``: nothing injected.
2. ``end_effect15``, ``end_effect20``: the force constant falling towards both ends of the
   stroke, K(x) = 1 - a ((x - xc)/(L/2))^2, xc = 0.2 m, L = 0.3 m, a = 0.15 and 0.20 (the end
   effect of a linear motor's finite magnet track / primary: I. Boldea, S. A. Nasar, "Linear
   Electric Actuators and Generators", Cambridge University Press, 1997; the parabola is this
   benchmark's shape, not the book's). The gain given to identify is K0.
3. ``encoder5um``: the reading rounded to 5 um counts with 1 um RMS white noise before the
   rounding (instead of the 1 um counts), nothing else. The loop reads that encoder too.
4. ``lugre40um``, ``lugre120um``: hysteretic friction in place of the Karnopp Coulomb term:
   LuGre without a Stribeck hump (Fs = Fc), i.e. Dahl's model with bristle damping:
   dz/dt = v - sigma0 |v| z / Fc, F = sigma0 z + sigma1 dz/dt + B v (P. R. Dahl, "A solid friction
   model", The Aerospace Corporation, TOR-0158(3107-18)-1, 1968; C. Canudas de Wit, H. Olsson,
   K. J. Astrom, P. Lischinsky, "A new model for control of systems with friction", IEEE Trans.
   Automatic Control 40(3), 1995). sigma0 = 3e5 and 1e5 N/m (presliding Fc/sigma0 = 40 and
   120 um), sigma1 = 1000 and 600 N s/m; z integrated exactly over each substep for its v.
5. ``two_periods``: two periodic forces of position at once, 4 N sin(2 pi x/17 mm + 0.3) and
   3 N sin(2 pi x/29 mm + 1.1) (cogging of a permanent-magnet linear motor at its slot and its
   pole pitch; e.g. G. Otten et al., "Linear motor motion control using a learning feedforward
   controller", IEEE/ASME Trans. Mechatronics 2(3), 1997, for its position-dependent force).
6. ``time_harmonic30``, ``time_harmonic45``: 4 N sin(2 pi f t + 0.4) from outside at an exact
   harmonic of the program, f = k/T, k = 30 (18.75 Hz) and 45 (28.125 Hz) (e.g. a neighbouring
   axis running a program on the same clock).
7. ``backlash100``, ``backlash150``: a two-mass plant: the motor carriage of 5 kg, the load of
   10 kg coupled through a play of +-100 and +-150 um (total 200, 300 um): the contact force
   k dz(x - xl) + c (v - vl) only beyond the gap, k = 1e7 N/m, c = 1500 N s/m (contact mode
   about 280 Hz); the encoder on the motor (M. Nordin, P.-O. Gutman, "Controlling mechanical
   systems with backlash - a survey", Automatica 38(10), 2002).
8. ``sticky_spot``: a local rise of the Coulomb level, +10 N exp(-(x - 0.27 m)^2 / (2 (10 mm)^2))
   (a contaminated or damaged spot of the guide).
9. ``payload5kg``: the mass +5 kg from t = 6 s (a part loaded mid-record).

**Classification** of identify's JSON (``effects``, ``ambiguous``, ``residual.structured``),
per record, in this order (A's cases; B's are classified the same way, with its own rule for
the plant's own names and the right and related families given with its cases below):

* The plant's own names are never wrong: ``stiction`` (the Karnopp or LuGre friction holds the
  carriage at rest) and ``stribeck`` with v_s <= 20 mm/s and 0 < F_s <= Fc (the plant's
  sign-shaped Coulomb friction against the model's S_f = (2/pi) atan(900 v): a friction
  falling with the speed within a few mm/s; identify names it on the clean records,
  v_s 5.8-7.6 mm/s, F_s 3.6-6.6 N).
* **wrong**: a named effect that is neither the plant's own nor among the case's right
  families, with or without a warning (for ``two_periods`` also a cogging at a period more than
  3 % from both 17 and 29 mm). The table gives the names; "+warning" marks those beside the
  verdict's warning.
* **right**: a right family named. ``clean``, ``encoder5um``: nothing beyond the plant's own
  and no warning and no ambiguity (a quantiser is not a force). ``end_effect*``:
  ``force_ripple`` (the family whose force is the thrust times a function of position; its
  periods reach only min(0.1 m, stroke/3), so it can only approximate a stroke-long
  parabola). ``two_periods``: ``cogging`` with **both** periods (within 3 %); the selection takes
  a family at most once, so one cogging term holds one period (and its second harmonic), and
  this outcome cannot occur with the present families; one period named with the warning is
  counted unexplained, without it missed. ``time_harmonic*``: ``periodic_disturbance``.
  ``sticky_spot``: ``position_friction_shape`` or its one-term case
  ``position_dependent_friction``. ``payload5kg``: ``payload_change``. ``lugre*``,
  ``backlash*``: none (no family models hysteretic friction or a play).
* **ambiguous**: an ``ambiguous`` entry whose two families include a right family or one
  describing a part of the effect's physics (``related``): end effect ``force_ripple``; LuGre
  ``stiction``, ``stribeck``, ``spring`` (the bristles are a spring at rest); two periods
  ``cogging``, ``force_ripple``, ``periodic_friction``; time harmonic ``periodic_disturbance``;
  backlash ``structural_mode``, ``amplifier_dead_zone`` (a two-mass coupling, a dead band);
  sticky spot the friction-of-position families and ``periodic_friction``; payload
  ``payload_change``. On ``clean``, ``encoder5um`` any ambiguity counts (a false alarm).
* **unexplained**: the residual verdict's warning (``residual.structured``), nothing wrong
  named. On ``clean``, ``encoder5um`` a warning is a false alarm.
* **missed**: none of these: no name beyond the plant's own and no warning (not used for
  ``clean``, ``encoder5um``).


**Simulation B** (``--sim b``: :func:`simulate_b`, :func:`program_b`; SI units). Written apart
from A and different from it wherever a realistic servo axis allows: mass, force gain, friction
law, loop structure, rate, program, record length and the effects' own implementations. Each
record is a CSV ``t,y,u`` of 10 s at 2 kHz (20000 samples), identified with ``--gain 25``.

* *Plant.* A carriage of M = 6 kg, F = K0 K(x) u with K0 = 25 N/V (K = 1 but in
  ``gain_slope10``), a white force noise of 0.15 N RMS held over each 0.5 ms sample, and the
  friction law F_f(v) = (Fc + (Fs - Fc) exp(-(v/vs)^2)) tanh(v/eps) + Bv with Coulomb
  Fc = 6 N, static (breakaway) Fs = 8 N, Stribeck velocity vs = 5 mm/s, viscous B = 8 N s/m
  (the Stribeck curve: B. Armstrong-Helouvry, P. Dupont, C. Canudas de Wit, "A survey of models,
  analysis tools and compensation methods for the control of machines with friction",
  Automatica 30(7), 1994), its zero crossing made smooth and steep by tanh with eps = 20 um/s
  (a continuously differentiable friction law as in C. Makkar, W. E. Dixon, W. G. Sawyer, G. Hu,
  "A new continuously differentiable friction model for control systems design", IEEE/ASME
  AIM 2005): below the breakaway force the carriage creeps at eps atanh(F/Fs), 11 um/s at
  F = Fs/2, instead of being held as in A. Integrated at 20 kHz (10 substeps per sample), the
  speed linearly implicit in the friction, v += h (F - F_f(v)) / (M + h max(F_f'(v), 0)), then
  x += h v; u held over each sample. The encoder reading is rounded to 0.5 um counts.
* *Loop* at 2 kHz, a cascade (e.g. G. Ellis, "Control System Design Guide", 4th ed.,
  Butterworth-Heinemann, 2012: position loop around a velocity loop, velocity and acceleration
  feedforward): the velocity estimate v_f is the reading's backward difference through a
  first-order low-pass at 400 Hz; the velocity command is v_d + Kpp (x_d - y), Kpp = 50 1/s; a
  PI velocity loop Kv = 70 V s/m, Ki = 3500 V/m (its zero at 50 rad/s) on the command minus
  v_f; plus a force feedforward 0.9 (M a_d + B v_d)/K0 (90 % of the true mass and viscous
  friction); u clipped at +-10 V, the integrator held while u is clipped. u is written after y
  is read and held over the sample, as in A. Open loop at u (a continuous model, the hold as
  half a sample): crossover 49 Hz, phase margin 60 deg, gain margin 27 dB, peak sensitivity
  1.2; with the 1.5 ms delay of ``delay1500us``: 33 deg, 2.2. Tracking error on the clean
  records 18.3 um RMS, 58 um at most, |u| <= 1.9 V; over all cases 17-25 um RMS, at most 117 um
  (after the 3 kg payload), |u| <= 3.5 V (the play): never clipped.
* *Program*, period T = 2.9 s (10 s: 3.45 periods), with B_XA = 0.11 m, B_XB = 0.23 m:
  (1) 1.2 s of a sum of sinusoids in position, x = B_XA + sum_k a_k (1 - cos(k w t)) +
  sum_k b_k sin(k w t), w = 2 pi / 1.2 s, a = (-30, 20, -12) mm, b = (12, -6) mm
  (sum_k k b_k = 0: it starts and ends at rest at B_XA), 0.025-0.121 m, peak 0.54 m/s and
  6 m/s^2, five reversals in motion (at 0.9-5.9 m/s^2); (2) 0.1 s dwell; (3) a trapezoidal
  move to B_XB at 0.5 m/s, 6 m/s^2 (ramps 83.5 ms, 0.32 s); (4) 0.15 s dwell; (5) back at
  0.12 m/s, 3 m/s^2 (ramps 40 ms, 1.04 s); (6) 0.0865 s dwell. Stroke 0.0247-0.23 m, middle
  x_m = 0.127 m.
* *Cases* (seeded like A's: the noises only). Not modelled by any family:

  1. ``clean``: nothing injected.
  2. ``gain_slope10``: the force constant linear in position, K(x) = 1 + 0.10 (x - x_m)/(L/2),
     L = 0.205 m the stroke: +-10 % at the stroke's ends (a magnet track or air gap varying
     along the stroke; this benchmark's shape). Right and related: ``force_ripple`` (as A's end
     effect: the family whose force is the thrust times a function of position; its periods
     reach only min(0.1 m, stroke/3) = 68 mm, so it can only approximate a slope).
  3. ``encoder2um``: the reading rounded to 2 um counts with 0.5 um RMS white noise before the
     rounding; the loop reads it too. A clean case (a quantiser is not a force).
  4. ``lugre_stribeck``: LuGre friction with B's Stribeck curve in place of B's friction law:
     dz/dt = v - sigma0 |v| z / g(v), g(v) = Fc + (Fs - Fc) exp(-(v/vs)^2),
     F = sigma0 z + sigma1 dz/dt + B v (Canudas de Wit et al. 1995, as A's), sigma0 = 1.5e5 N/m
     (presliding Fc/sigma0 = 40 um, Fs/sigma0 = 53 um), sigma1 = 300 N s/m (bristle damping
     ratio sigma1 / (2 sqrt(sigma0 M)) = 0.16); z integrated exactly over each substep for its v.
     Right: none; related ``stiction``, ``stribeck``, ``spring``.
  5. ``two_periods``: 3 N sin(2 pi x/11 mm + 0.5) + 2.5 N sin(2 pi x/23 mm + 2.0). Right:
     ``cogging`` with both periods within 3 % (as A's: the selection takes a family once, so
     this outcome cannot occur); a cogging more than 3 % from both periods is wrong, also when
     its second harmonic is near 11 mm. Related ``cogging``, ``force_ripple``,
     ``periodic_friction``.
  6. ``time_harmonic47``: 3 N sin(2 pi f t + 0.9) at an exact harmonic of the program,
     f = 47/T = 16.207 Hz. Right and related ``periodic_disturbance`` (at any frequency, as A's).
  7. ``play80um``: a two-mass plant: the motor carriage of 2.5 kg (the encoder on it), the load
     of 3.5 kg on its own guide, each with its mass share of B's friction law (Fc, Fs and B times
     2.5/6 and 3.5/6), coupled through a play of +-80 um: the contact force
     k dz(x - xl) + c (v - vl) only beyond the gap, k = 5e6 N/m, c = 600 N s/m (contact mode
     295 Hz), the load's speed implicit in its friction as the carriage's. Right: none; related
     ``structural_mode``, ``amplifier_dead_zone`` (as A's backlash).

  Modelled by a family, to check that identify names it right:

  8. ``cogging19``: 3 N sin(2 pi x/19 mm + 1.3). Right: ``cogging`` within 3 % of 19 mm (another
     period is wrong). Related ``cogging``, ``force_ripple``, ``periodic_friction``.
  9. ``disturbance13``: 3 N sin(2 pi 13.3 Hz t + 0.4), 13.3 T = 38.57: not a harmonic of the
     program. Right: ``periodic_disturbance`` within 3 % of 13.3 Hz (another frequency is
     wrong). Related ``periodic_disturbance``.
  10. ``delay1500us``: u acts 3 samples (1.5 ms) after the loop wrote it, beyond the hold (a
      transport delay: e.g. a fieldbus cycle); the loop's margins above. Right and related
      ``input_delay`` (its value is printed, not judged: with the hold the whole delay is
      3.5 samples, 1.75 ms).
  11. ``spring60``: -60 N/m (x - x_m) (a cable chain or bellows pulling towards mid-stroke).
      Right and related ``spring`` (the stiffness printed, not judged).
  12. ``payload3kg``: the mass +3 kg from t = 5 s. Right and related ``payload_change`` (the
      mass printed, not judged; t = 5.0-5.67 s is the slow move's cruise, where no acceleration
      tells the mass, so any step time there fits alike).

* *The plant's own names for B*: ``stiction`` (the steep friction law holds the carriage nearly
  still below Fs) and ``stribeck`` with v_s <= 20 mm/s (4 vs: the hump's exp(-(v/vs)^2) is
  below 0.02 at 10 mm/s, and S_f = (2/pi) atan(900 v), against which the plant's tanh crossing
  is a friction falling with the speed, reaches 0.9 at 7 mm/s, 0.95 at 14 mm/s) and the force
  the term adds, max over v of F_s exp(-(v/v_s)^2) S_f(v), in (0, Fs = 8 N] (at v -> 0+ the
  plant's friction is Fs while the model's Coulomb term theta3 S_f(v) goes to 0: the hump,
  Fs - Fc = 2 N, plus the sign shape's excess over S_f, up to Fc). The bound is on the force,
  not on F_s as in A's rule: the term's column carries S_f(v), 0.47 at 1 mm/s, so a Stribeck
  term fitting the plant's friction at a few mm/s has F_s above the force it adds (measured:
  F_s 9.3-11.5 N at v_s 3.6-4.2 mm/s beside a cogging or a payload, a force of 5.0-5.8 N at
  1.7-1.9 mm/s; A's rule would have counted those 6 records wrong).

What a user needs is never a single confident wrong name: the wrong column should be 0.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from multiprocessing import Pool
from pathlib import Path

import numpy as np

# ---------------------------------------------------------------------------------------------
# the plant, the loop and the program (SI units throughout)
# ---------------------------------------------------------------------------------------------
#: sample rate of the loop and the record [Hz], record length [s], plant substeps per sample
FS, DURATION_S, SUB = 1000.0, 12.0, 10
#: carriage mass [kg], force gain K0 [N/V] (the --gain given to identify), viscous [N s/m],
#: Coulomb [N], force noise on the carriage [N RMS per sample], encoder count [m]
M, A1, B, FC, F_NOISE, COUNT = 15.0, 40.0, 25.0, 12.0, 0.2, 1e-6
#: the program: a cycloidal move X0 -> X0 + STROKE in T_MOVE, a dwell T_DWELL, back, a dwell:
#: period T_PROG = 2 (T_MOVE + T_DWELL) [s]; peak speed 2 STROKE / T_MOVE = 1 m/s, peak
#: acceleration 2 pi STROKE / T_MOVE^2 = 5.2 m/s^2
X0, STROKE, T_MOVE, T_DWELL = 0.05, 0.30, 0.6, 0.2
T_PROG = 2 * (T_MOVE + T_DWELL)
#: the loop: PID on the reading [V/m, V/(m s), V s/m], its derivative's low-pass [Hz], feedforward
#: of the reference's acceleration and speed at 95 % of the true mass and viscous friction
KP, KI, KD, D_LP_HZ, FF_SHARE = 12000.0, 2.0e5, 90.0, 300.0, 0.95


def program(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reference position, speed and acceleration (n,) each [m, m/s, m/s^2] at FS: the
    cycloid x = X0 + STROKE (tau - sin(2 pi tau)/(2 pi)), tau = t/T_MOVE, out and back with dwells,
    repeated with period T_PROG."""
    nm, nd = int(round(T_MOVE * FS)), int(round(T_DWELL * FS))
    tau = np.arange(nm) / nm
    up = X0 + STROKE * (tau - np.sin(2 * np.pi * tau) / (2 * np.pi))
    vup = STROKE / T_MOVE * (1 - np.cos(2 * np.pi * tau))
    aup = STROKE / T_MOVE ** 2 * 2 * np.pi * np.sin(2 * np.pi * tau)
    top, bot = X0 + STROKE, X0
    x1 = np.concatenate([up, np.full(nd, top), 2 * X0 + STROKE - up, np.full(nd, bot)])
    v1 = np.concatenate([vup, np.zeros(nd), -vup, np.zeros(nd)])
    a1 = np.concatenate([aup, np.zeros(nd), -aup, np.zeros(nd)])
    reps = n // len(x1) + 1
    return np.tile(x1, reps)[:n], np.tile(v1, reps)[:n], np.tile(a1, reps)[:n]


def simulate(case: dict, seed: int, path: str | os.PathLike) -> str:
    """Simulate the loop on the plant with ``case``'s effect and write ``t,y,u`` [s, m, V] to a
    CSV at ``path``. Returns the path as text. See the module docstring for the physics."""
    rng = np.random.default_rng(seed)
    n = int(round(DURATION_S * FS))
    ts = 1.0 / FS
    h = ts / SUB
    xd, vd, ad = program(n)
    t = np.arange(n) * ts
    count = case.get("count_m", COUNT)
    enc_noise = case.get("enc_noise_m", 0.0)
    y_noise = rng.normal(0.0, 1.0, n) * enc_noise
    f_noise = rng.normal(0.0, F_NOISE, n)
    # effects (each off unless the case sets it)
    end_a = case.get("end_a", 0.0)                      # K(x) = K0 (1 - a ((x - xc)/(L/2))^2)
    xc, half = X0 + STROKE / 2, STROKE / 2
    cog = case.get("cogging", ())                       # ((amplitude N, period m, phase rad), ...)
    dist = case.get("time_force")                       # (amplitude N, frequency Hz, phase rad)
    lugre = case.get("lugre")                           # (sigma0 N/m, sigma1 N s/m)
    gap = case.get("gap_m", 0.0)                        # backlash: half-gap [m] (0: rigid)
    spot = case.get("spot")                             # (extra Coulomb N, centre m, sigma m)
    payload = case.get("payload")                       # (extra mass kg, time s)
    m_motor = M
    if gap:
        m_load = case.get("load_kg", 10.0)
        m_motor = M - m_load
        k_c, c_c = case.get("contact_N_per_m", 1.0e7), case.get("contact_Ns_per_m", 1500.0)
    # states: carriage (motor) x, v; load xl, vl; LuGre bristle z; loop integrator, D filter
    vx = 0.0
    x = xl = X0
    vl = 0.0
    z = 0.0
    e_int = 0.0
    y_prev = None
    d_f = 0.0
    alpha = 1.0 - math.exp(-2 * math.pi * D_LP_HZ * ts)
    ys, us = np.empty(n), np.empty(n)
    for i in range(n):
        # the reading: quantised (round to the count), optional noise before it
        y = count * round((x + y_noise[i]) / count) if count else x + y_noise[i]
        e = xd[i] - y
        e_int += e * ts
        de = (e - (xd[i - 1] - y_prev)) / ts if y_prev is not None else 0.0
        d_f += alpha * (de - d_f)
        y_prev = y
        ff = FF_SHARE * (M * ad[i] + B * vd[i]) / A1
        u = ff + KP * e + KI * e_int + KD * d_f
        u = min(10.0, max(-10.0, u))
        ti = t[i]
        m_now = m_motor + (payload[0] if payload and ti >= payload[1] else 0.0)
        for j in range(SUB):
            k_x = 1.0 - end_a * ((x - xc) / half) ** 2 if end_a else 1.0
            f = A1 * k_x * u + f_noise[i]
            for amp, per, ph in cog:
                f += amp * math.sin(2 * math.pi * x / per + ph)
            if dist:
                f += dist[0] * math.sin(2 * math.pi * dist[1] * (ti + j * h) + dist[2])
            if gap:                                  # the load held with a play of +-gap
                dxr = x - xl
                pen = dxr - gap if dxr > gap else (dxr + gap if dxr < -gap else 0.0)
                fc_ = k_c * pen + c_c * (vx - vl) if pen else 0.0
                f -= fc_
                vl += fc_ / m_load * h
                xl += vl * h
            fc_lvl = FC
            if spot:
                fc_lvl += spot[0] * math.exp(-0.5 * ((x - spot[1]) / spot[2]) ** 2)
            if lugre:                                # LuGre without Stribeck (Dahl + bristle damping)
                s0, s1 = lugre
                z_ss = fc_lvl / s0 * (1.0 if vx > 0 else -1.0)
                # z' = v - s0 |v| z / Fc, integrated exactly for a constant v over the substep
                z_new = z_ss + (z - z_ss) * math.exp(-s0 * abs(vx) * h / fc_lvl)
                dz, z = (z_new - z) / h, z_new
                f_fr = s0 * z + s1 * dz + B * vx
                vx += (f - f_fr) / m_now * h
            else:                                    # Karnopp: held below the Coulomb level
                if vx == 0.0:
                    if abs(f) <= fc_lvl:
                        continue
                    vx = (f - fc_lvl * (1.0 if f > 0 else -1.0)) / m_now * h
                else:
                    v_new = vx + (f - fc_lvl * (1.0 if vx > 0 else -1.0) - B * vx) / m_now * h
                    vx = 0.0 if v_new * vx < 0.0 else v_new      # stops where it crosses zero
            x += vx * h
        ys[i], us[i] = y, u
    np.savetxt(path, np.column_stack([t, ys, us]), delimiter=",", header="t,y,u", comments="",
               fmt=["%.4f", "%.9f", "%.6f"])
    return str(path)


# ---------------------------------------------------------------------------------------------
# simulation B: another axis, loop, program and effects (SI units throughout)
# ---------------------------------------------------------------------------------------------
#: sample rate of the loop and the record [Hz], record length [s], plant substeps per sample
B_FS, B_DURATION_S, B_SUB = 2000.0, 10.0, 10
#: carriage mass [kg], force gain K0 [N/V] (the --gain given to identify), viscous [N s/m],
#: Coulomb and static (breakaway) friction [N], Stribeck velocity [m/s], the zero crossing's
#: velocity scale [m/s] (tanh), force noise [N RMS per sample], encoder count [m]
B_M, B_K0, B_VISC, B_FC, B_FSTAT, B_VS, B_VEPS, B_F_NOISE, B_COUNT = (
    6.0, 25.0, 8.0, 6.0, 8.0, 0.005, 2.0e-5, 0.15, 0.5e-6)
#: the program: a sum of sinusoids in position (B_SINE_T s, from and back to B_XA at rest:
#: x = B_XA + sum a_k (1 - cos(k w t)) + sum b_k sin(k w t), w = 2 pi / B_SINE_T, sum k b_k = 0),
#: a dwell, a trapezoidal move B_XA -> B_XB at the fast speed, a dwell, back at the slow speed,
#: a dwell: each move's (ramp samples, cruise samples), its speed its distance over
#: (ramp + cruise) time, the acceleration its speed over the ramp
B_XA, B_XB, B_SINE_T = 0.11, 0.23, 1.2
B_SINE_A, B_SINE_B = (-0.03, 0.02, -0.012), (0.012, -0.006)
B_FAST, B_SLOW = (167, 313), (80, 1920)                  # 0.5 m/s at 6 m/s^2; 0.12 m/s at 3 m/s^2
B_DWELLS = (0.1, 0.15, 0.0865)                            # after the sinusoids, the fast move, the slow
B_T_PROG = B_SINE_T + sum(B_DWELLS) + (2 * B_FAST[0] + B_FAST[1] + 2 * B_SLOW[0] + B_SLOW[1]) / B_FS
#: the cascade at B_FS: P position loop [1/s] -> PI velocity loop [V s/m, V/m] on the reading's
#: difference through a first-order low-pass [Hz]; the velocity command is the reference's speed
#: plus the position loop's; force feedforward of the reference's acceleration and speed at
#: B_FF_SHARE of the true mass and viscous friction; u clipped at +-B_U_MAX [V], the integrator
#: held while u is clipped
B_KPP, B_KV, B_KVI, B_V_LP_HZ, B_FF_SHARE, B_U_MAX = 50.0, 70.0, 3500.0, 400.0, 0.90, 10.0


def program_b(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulation B's reference position, speed and acceleration (n,) each [m, m/s, m/s^2] at
    B_FS: the sum of sinusoids, then the trapezoidal moves with dwells, repeated with period
    B_T_PROG (module docstring)."""
    ts = 1.0 / B_FS
    w = 2 * np.pi / B_SINE_T
    t = np.arange(int(round(B_SINE_T * B_FS))) * ts
    xs = B_XA + sum(a * (1 - np.cos((k + 1) * w * t)) for k, a in enumerate(B_SINE_A)) \
        + sum(b * np.sin((k + 1) * w * t) for k, b in enumerate(B_SINE_B))
    vs = sum(a * (k + 1) * w * np.sin((k + 1) * w * t) for k, a in enumerate(B_SINE_A)) \
        + sum(b * (k + 1) * w * np.cos((k + 1) * w * t) for k, b in enumerate(B_SINE_B))
    acs = sum(a * ((k + 1) * w) ** 2 * np.cos((k + 1) * w * t) for k, a in enumerate(B_SINE_A)) \
        - sum(b * ((k + 1) * w) ** 2 * np.sin((k + 1) * w * t) for k, b in enumerate(B_SINE_B))
    parts_x, parts_v, parts_a = [xs], [vs], [acs]

    def dwell(x, dur):
        nd = int(round(dur * B_FS))
        parts_x.append(np.full(nd, x)), parts_v.append(np.zeros(nd)), parts_a.append(np.zeros(nd))

    def move(x0, x1, ramp, cruise):
        # piecewise-constant acceleration on the sample grid, integrated exactly
        vmax = (x1 - x0) / ((ramp + cruise) * ts)
        acc = np.concatenate([np.full(ramp, vmax / (ramp * ts)), np.zeros(cruise), np.full(ramp, -vmax / (ramp * ts))])
        v = np.concatenate([[0.0], np.cumsum(acc) * ts])
        x = x0 + np.concatenate([[0.0], np.cumsum(v[:-1] * ts + acc * ts ** 2 / 2)])
        parts_x.append(x[:-1]), parts_v.append(v[:-1]), parts_a.append(acc)

    dwell(B_XA, B_DWELLS[0])
    move(B_XA, B_XB, *B_FAST)
    dwell(B_XB, B_DWELLS[1])
    move(B_XB, B_XA, *B_SLOW)
    dwell(B_XA, B_DWELLS[2])
    x1, v1, a1 = np.concatenate(parts_x), np.concatenate(parts_v), np.concatenate(parts_a)
    reps = n // len(x1) + 1
    return np.tile(x1, reps)[:n], np.tile(v1, reps)[:n], np.tile(a1, reps)[:n]


#: simulation B's stroke [m] (the program's extent) and its middle
_XB_REF = program_b(int(round(B_T_PROG * B_FS)))[0]
B_XMIN, B_XMAX = float(_XB_REF.min()), float(_XB_REF.max())
B_XMID = 0.5 * (B_XMIN + B_XMAX)


def _friction_b(v: float, fc: float, fs: float, visc: float) -> tuple[float, float]:
    """Simulation B's friction force [N] at speed v [m/s] and its derivative in v [N s/m]:
    (fc + (fs - fc) exp(-(v/B_VS)^2)) tanh(v/B_VEPS) + visc v."""
    e = math.exp(-(v / B_VS) ** 2)
    g = fc + (fs - fc) * e
    th = math.tanh(v / B_VEPS)
    return g * th + visc * v, g * (1.0 - th * th) / B_VEPS - 2.0 * (fs - fc) * e * v / B_VS ** 2 * th + visc


def simulate_b(case: dict, seed: int, path: str | os.PathLike) -> str:
    """Simulation B: the cascade on B's plant with ``case``'s effect; writes ``t,y,u`` [s, m, V]
    to a CSV at ``path``. Returns the path as text. See the module docstring for the physics."""
    rng = np.random.default_rng(seed)
    n = int(round(B_DURATION_S * B_FS))
    ts = 1.0 / B_FS
    h = ts / B_SUB
    xd, vd, ad = program_b(n)
    t = np.arange(n) * ts
    count = case.get("count_m", B_COUNT)
    y_noise = rng.normal(0.0, 1.0, n) * case.get("enc_noise_m", 0.0)
    f_noise = rng.normal(0.0, B_F_NOISE, n)
    grad = case.get("gain_slope", 0.0)                  # K(x) = 1 + g (x - xmid)/(stroke/2)
    half = 0.5 * (B_XMAX - B_XMIN)
    cog = case.get("cogging", ())                       # ((amplitude N, period m, phase rad), ...)
    dist = case.get("time_force", ())                   # ((amplitude N, frequency Hz, phase rad), ...)
    lugre = case.get("lugre")                           # (sigma0 N/m, sigma1 N s/m), Stribeck as the plant's
    gap = case.get("gap_m", 0.0)                        # play: half-gap [m]
    delay = case.get("delay_samples", 0)                # u acts this many samples late
    k_spring = case.get("spring_N_per_m", 0.0)          # -k (x - B_XMID)
    payload = case.get("payload")                       # (extra mass kg, time s)
    m_car, fc, fs, visc = B_M, B_FC, B_FSTAT, B_VISC
    if gap:                                             # carriage and load, each on its own guide
        m_load = case.get("load_kg", 3.5)
        share = m_load / B_M
        m_car = B_M - m_load
        fc, fs, visc = B_FC * (1 - share), B_FSTAT * (1 - share), B_VISC * (1 - share)
        k_c, c_c = case.get("contact_N_per_m", 5.0e6), case.get("contact_Ns_per_m", 600.0)
    x = xl = xd[0]
    vx = vl = z = 0.0
    v_f = v_int = 0.0
    y_prev = None
    alpha = 1.0 - math.exp(-2 * math.pi * B_V_LP_HZ * ts)
    u_hist = [0.0] * delay
    ys, us = np.empty(n), np.empty(n)
    for i in range(n):
        y = count * round((x + y_noise[i]) / count) if count else x + y_noise[i]
        v_f += alpha * (((y - y_prev) / ts if y_prev is not None else 0.0) - v_f)
        y_prev = y
        v_err = vd[i] + B_KPP * (xd[i] - y) - v_f
        ff = B_FF_SHARE * (B_M * ad[i] + B_VISC * vd[i]) / B_K0
        u = ff + B_KV * v_err + B_KVI * (v_int + v_err * ts)
        if -B_U_MAX < u < B_U_MAX:                     # the integrator held while clipped
            v_int += v_err * ts
        u = min(B_U_MAX, max(-B_U_MAX, u))
        u_hist.append(u)
        u_act = u_hist.pop(0)                           # the u acting over this sample
        ti = t[i]
        m_now = m_car + (payload[0] if payload and ti >= payload[1] else 0.0)
        for j in range(B_SUB):
            k_x = 1.0 + grad * (x - B_XMID) / half if grad else 1.0
            f = B_K0 * k_x * u_act + f_noise[i]
            for amp, per, ph in cog:
                f += amp * math.sin(2 * math.pi * x / per + ph)
            for amp, fq, ph in dist:
                f += amp * math.sin(2 * math.pi * fq * (ti + j * h) + ph)
            if k_spring:
                f -= k_spring * (x - B_XMID)
            if gap:
                dxr = x - xl
                pen = dxr - gap if dxr > gap else (dxr + gap if dxr < -gap else 0.0)
                f_c = k_c * pen + c_c * (vx - vl) if pen else 0.0
                f -= f_c
                ffl, dfl = _friction_b(vl, B_FC * share, B_FSTAT * share, B_VISC * share)
                vl += h * (f_c - ffl) / (m_load + h * max(dfl, 0.0))
                xl += vl * h
            if lugre:                                   # LuGre with B's Stribeck curve
                s0, s1 = lugre
                g = fc + (fs - fc) * math.exp(-(vx / B_VS) ** 2)
                z_ss = g / s0 * (1.0 if vx > 0 else -1.0)
                z_new = z_ss + (z - z_ss) * math.exp(-s0 * abs(vx) * h / g)
                dz, z = (z_new - z) / h, z_new
                vx += (f - (s0 * z + s1 * dz + visc * vx)) / m_now * h
            else:                                       # B's friction, linearly implicit in v
                f_fr, df = _friction_b(vx, fc, fs, visc)
                vx += h * (f - f_fr) / (m_now + h * max(df, 0.0))
            x += vx * h
        ys[i], us[i] = y, u
    np.savetxt(path, np.column_stack([t, ys, us]), delimiter=",", header="t,y,u", comments="",
               fmt=["%.4f", "%.9f", "%.6f"])
    return str(path)


# ---------------------------------------------------------------------------------------------
# the cases and what is accepted for each
# ---------------------------------------------------------------------------------------------
#: the plant's own names beside any case: stiction (the Karnopp/LuGre friction holds the carriage
#: at rest up to its Coulomb level) and a Stribeck term of at most FC [N] below STRIBECK_OWN_V
#: [m/s] (the plant's sign-shaped Coulomb friction against the model's S_f = (2/pi) atan(900 v),
#: a friction falling with the speed within a few mm/s)
STRIBECK_OWN_V = 0.02

#: name -> (the plant's changes for :func:`simulate`, kind, right families, related families, text).
#: kind "clean": nothing beyond the plant's own is right (no "missed"); "effect": as below.
CASES = {
    "clean": ({}, "clean", set(), set(), "nothing injected"),
    "end_effect15": ({"end_a": 0.15}, "effect", {"force_ripple"}, {"force_ripple"},
                     "force constant -15 % at both stroke ends (parabola)"),
    "end_effect20": ({"end_a": 0.20}, "effect", {"force_ripple"}, {"force_ripple"},
                     "force constant -20 % at both stroke ends (parabola)"),
    "encoder5um": ({"count_m": 5e-6, "enc_noise_m": 1e-6}, "clean", set(), set(),
                   "5 um counts + 1 um RMS reading noise"),
    "lugre40um": ({"lugre": (3.0e5, 1000.0)}, "effect", set(), {"stiction", "stribeck", "spring"},
                  "LuGre/Dahl friction, presliding Fc/sigma0 = 40 um"),
    "lugre120um": ({"lugre": (1.0e5, 600.0)}, "effect", set(), {"stiction", "stribeck", "spring"},
                   "LuGre/Dahl friction, presliding Fc/sigma0 = 120 um"),
    "two_periods": ({"cogging": ((4.0, 0.017, 0.3), (3.0, 0.029, 1.1))}, "effect", {"cogging"},
                    {"cogging", "force_ripple", "periodic_friction"}, "4 N at 17 mm + 3 N at 29 mm"),
    "time_harmonic30": ({"time_force": (4.0, 30 / T_PROG, 0.4)}, "effect", {"periodic_disturbance"},
                        {"periodic_disturbance"}, "4 N at 18.75 Hz = 30/T"),
    "time_harmonic45": ({"time_force": (4.0, 45 / T_PROG, 0.4)}, "effect", {"periodic_disturbance"},
                        {"periodic_disturbance"}, "4 N at 28.125 Hz = 45/T"),
    "backlash100": ({"gap_m": 1.0e-4}, "effect", set(), {"structural_mode", "amplifier_dead_zone"},
                    "10 kg load with a +-100 um play"),
    "backlash150": ({"gap_m": 1.5e-4}, "effect", set(), {"structural_mode", "amplifier_dead_zone"},
                    "10 kg load with a +-150 um play"),
    "sticky_spot": ({"spot": (10.0, 0.27, 0.01)}, "effect", {"position_friction_shape", "position_dependent_friction"},
                    {"position_friction_shape", "position_dependent_friction", "periodic_friction"},
                    "+10 N Coulomb, Gaussian sigma 10 mm at 0.27 m"),
    "payload5kg": ({"payload": (5.0, 6.0)}, "effect", {"payload_change"}, {"payload_change"},
                   "+5 kg at t = 6 s"),
}
#: the two periods of "two_periods" [m]: cogging is right only when it finds both (within 3 %)
TWO_PERIODS = (0.017, 0.029)
OUTCOMES = ("right", "ambiguous", "unexplained", "wrong", "missed")

#: simulation B's own Stribeck names: v_s at most this [m/s] (4 B_VS) and the force the term adds,
#: max over v of F_s exp(-(v/v_s)^2) S_f(v), S_f = (2/pi) atan(900 v), in (0, B_FSTAT] [N]
B_STRIBECK_OWN_V = 0.02


def _stribeck_own_a(p: dict) -> bool:
    """Simulation A's rule for a named Stribeck term (parameters ``p``): v_s <= STRIBECK_OWN_V,
    0 < F_s <= FC."""
    return p.get("stribeck_velocity_m_per_s", 1.0) <= STRIBECK_OWN_V and 0.0 < p.get("force_N", 1e9) <= FC


def _stribeck_own_b(p: dict) -> bool:
    """Simulation B's rule for a named Stribeck term (parameters ``p``): v_s <= B_STRIBECK_OWN_V
    and the largest force it adds, max_v F_s exp(-(v/v_s)^2) S_f(v), in (0, B_FSTAT]."""
    vs, fs = p.get("stribeck_velocity_m_per_s", 1.0), p.get("force_N", 1e9)
    if not 0.0 < vs <= B_STRIBECK_OWN_V:
        return False
    v = np.linspace(0.0, 4.0 * vs, 801)
    peak = fs * float(np.max(np.exp(-(v / vs) ** 2) * (2 / np.pi) * np.arctan(900.0 * v)))
    return 0.0 < peak <= B_FSTAT
#: simulation B's harmonic of the program for its time-periodic force, and its non-harmonic
#: periodic disturbance [Hz] (13.3 B_T_PROG = 38.57: as far from a harmonic as a half)
B_HARMONIC, B_DIST_HZ = 47, 13.3
#: simulation B's cases, as CASES
CASES_B = {
    "clean": ({}, "clean", set(), set(), "nothing injected"),
    "gain_slope10": ({"gain_slope": 0.10}, "effect", {"force_ripple"}, {"force_ripple"},
                     "force constant linear in position, +-10 % over the stroke"),
    "encoder2um": ({"count_m": 2e-6, "enc_noise_m": 0.5e-6}, "clean", set(), set(),
                   "2 um counts + 0.5 um RMS reading noise"),
    "lugre_stribeck": ({"lugre": (1.5e5, 300.0)}, "effect", set(), {"stiction", "stribeck", "spring"},
                       "LuGre with B's Stribeck curve, presliding Fc/sigma0 = 40 um"),
    "two_periods": ({"cogging": ((3.0, 0.011, 0.5), (2.5, 0.023, 2.0))}, "effect", {"cogging"},
                    {"cogging", "force_ripple", "periodic_friction"}, "3 N at 11 mm + 2.5 N at 23 mm"),
    f"time_harmonic{B_HARMONIC}": ({"time_force": ((3.0, B_HARMONIC / B_T_PROG, 0.9),)}, "effect",
                                   {"periodic_disturbance"}, {"periodic_disturbance"},
                                   f"3 N at {B_HARMONIC / B_T_PROG:.3f} Hz = {B_HARMONIC}/T"),
    "play80um": ({"gap_m": 8.0e-5}, "effect", set(), {"structural_mode", "amplifier_dead_zone"},
                 "3.5 kg load on a 2.5 kg carriage, +-80 um play"),
    "cogging19": ({"cogging": ((3.0, 0.019, 1.3),)}, "effect", {"cogging"},
                  {"cogging", "force_ripple", "periodic_friction"}, "modelled: 3 N at 19 mm"),
    "disturbance13": ({"time_force": ((3.0, B_DIST_HZ, 0.4),)}, "effect", {"periodic_disturbance"},
                      {"periodic_disturbance"}, f"modelled: 3 N at {B_DIST_HZ} Hz = {B_DIST_HZ * B_T_PROG:.2f}/T"),
    "delay1500us": ({"delay_samples": 3}, "effect", {"input_delay"}, {"input_delay"},
                    "modelled: u acts 1.5 ms late (3 samples)"),
    "spring60": ({"spring_N_per_m": 60.0}, "effect", {"spring"}, {"spring"},
                 "modelled: 60 N/m towards mid-stroke"),
    "payload3kg": ({"payload": (3.0, 5.0)}, "effect", {"payload_change"}, {"payload_change"},
                   "modelled: +3 kg at t = 5 s"),
}

#: the simulations: their simulate(case changes, seed, path), cases, force gain given to identify
#: [N/V], the plant's own rule for a named Stribeck term (stiction is always the plant's own), the cases whose
#: right family must have the injected values of a parameter (family, JSON key, values: each
#: named term within 3 % of one of them, else wrong; right only when all are found) and the
#: prefix of the kept files
SIMS = {
    "a": {"simulate": simulate, "cases": CASES, "gain": A1, "stribeck_own": _stribeck_own_a,
          "targets": {"two_periods": ("cogging", "period_m", TWO_PERIODS)}, "prefix": ""},
    "b": {"simulate": simulate_b, "cases": CASES_B, "gain": B_K0, "stribeck_own": _stribeck_own_b,
          "targets": {"two_periods": ("cogging", "period_m", (0.011, 0.023)),
                      "cogging19": ("cogging", "period_m", (0.019,)),
                      "disturbance13": ("periodic_disturbance", "frequency_Hz", (B_DIST_HZ,))},
          "prefix": "b_"},
}


def _own(e: dict, sim: str = "a") -> bool:
    """Whether a named effect (identify's JSON ``effects`` entry) is simulation ``sim``'s plant's own."""
    if e["name"] == "stiction":
        return True
    if e["name"] == "stribeck":
        return SIMS[sim]["stribeck_own"](e["parameters"])
    return False


def _label(e: dict) -> str:
    """A named effect with its main parameter, e.g. ``spring -35.9 N/m``."""
    p = e["parameters"]
    for key, fmt in (("period_m", "{:.1f} mm"), ("frequency_Hz", "{:.2f} Hz"), ("stiffness_N_per_m", "{:.1f} N/m"),
                     ("mass_kg", "{:+.2f} kg"), ("delay_s", "{:.2e} s"), ("dead_zone_V", "{:.3f} V"),
                     ("antiresonance_Hz", "{:.0f} Hz"), ("stribeck_velocity_m_per_s", "{:.3f} m/s")):
        if key in p and isinstance(p[key], (int, float)):
            v = p[key] * (1e3 if key == "period_m" else 1.0)
            return f"{e['name']} {fmt.format(v)}"
    return e["name"]


def classify(case: str, s: dict, sim: str = "a") -> tuple[str, str]:
    """(outcome, detail) of identify's JSON summary ``s`` for simulation ``sim``'s ``case``
    (module docstring)."""
    _, kind, right, related, _ = SIMS[sim]["cases"][case]
    target = SIMS[sim]["targets"].get(case)
    fam, key, values = target or (None, None, ())
    named = [e for e in s["effects"] if not _own(e, sim)]
    amb = [a for a in s.get("ambiguous", [])]
    warned = bool(s["residual"]["structured"])
    found = [p0 for p0 in values if any(abs(e["parameters"][key] / p0 - 1) < 0.03 for e in named if e["name"] == fam)]
    wrong = []
    for e in named:
        if e["name"] not in right or (e["name"] == fam and not any(
                abs(e["parameters"][key] / p0 - 1) < 0.03 for p0 in values)):
            wrong.append(_label(e) + (" +warning" if warned else ""))
    detail = "; ".join([_label(e) for e in named] + [a["text"].split(":")[0] for a in amb]
                       + (["warning"] if warned else []))
    if wrong:
        return "wrong", ", ".join(wrong)
    if kind == "clean":
        if amb:
            return "ambiguous", detail
        return ("unexplained", detail) if warned else ("right", detail)
    if target:
        if len(found) == len(values):
            return "right", detail
    elif named:
        return "right", detail
    if any(set(a["families"]) & (right | related) for a in amb):
        return "ambiguous", detail
    return ("unexplained", detail) if warned else ("missed", detail)


def run_one(job: tuple[str, int, str, float | None, str]) -> dict:
    """Simulate simulation ``sim``'s ``case`` at ``seed`` into ``folder``, identify the CSV
    through the CLI (``sys.executable -m motorctl identify CSV --gain GAIN --json``, the
    simulation's force gain, with ``--zoh-delay`` when ``zoh`` [samples] is not None), classify.
    Returns a row."""
    case, seed, folder, zoh, sim = job
    cfg = SIMS[sim]
    path = Path(folder) / f"{cfg['prefix']}{case}_seed{seed}.csv"
    t0 = time.perf_counter()
    cfg["simulate"](cfg["cases"][case][0], seed, path)
    t1 = time.perf_counter()
    cmd = [sys.executable, "-m", "motorctl", "identify", str(path), "--gain", f"{cfg['gain']:g}", "--json"]
    if zoh is not None:
        cmd += ["--zoh-delay", f"{zoh:g}"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    t2 = time.perf_counter()
    row = {"case": case, "seed": seed, "sim_s": t1 - t0, "identify_s": t2 - t1, "csv": str(path)}
    if r.returncode != 0:
        row.update(outcome="error", detail=(r.stderr.strip().splitlines() or ["?"])[-1], stderr=r.stderr)
        return row
    s = json.loads(r.stdout)
    path.with_suffix(".json").write_text(r.stdout)
    outcome, detail = classify(case, s, sim)
    row.update(outcome=outcome, detail=detail, effects=[_label(e) for e in s["effects"]],
               ambiguous=[a["text"] for a in s.get("ambiguous", [])], warning=s["residual"]["text"]
               if s["residual"]["structured"] else "")
    return row


def table(rows: list[dict], cases: list[str], seeds: list[int], sim: str = "a") -> str:
    """The Markdown table: per case the seeds, the outcome counts and the wrong names given."""
    seed_txt = f"{seeds[0]}-{seeds[-1]}" if seeds == list(range(seeds[0], seeds[-1] + 1)) and len(seeds) > 1 \
        else ",".join(map(str, seeds))
    out = ["| case | injected | seeds | right | ambiguous | unexplained | wrong | missed | wrong names given |",
           "|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        rs = [r for r in rows if r["case"] == c]
        n = {o: sum(r["outcome"] == o for r in rs) for o in OUTCOMES}
        err = sum(r["outcome"] == "error" for r in rs)
        wrong = "; ".join(f"seed {r['seed']}: {r['detail']}" for r in rs if r["outcome"] == "wrong") or "-"
        if err:
            wrong += f" ({err} errors)"
        out.append(f"| {c} | {SIMS[sim]['cases'][c][4]} | {seed_txt} | " + " | ".join(str(n[o]) for o in OUTCOMES)
                   + f" | {wrong} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="1-3", help="seeds: N, N-M or a comma list (default 1-3)")
    ap.add_argument("--sim", choices=list(SIMS), default="a",
                    help="the simulation: a (the PID loop, default) or b (the cascade on a 6 kg axis)")
    ap.add_argument("--case", action="append", metavar="CASE",
                    help="only these cases of the simulation (repeatable; default all): a: " + ", ".join(CASES)
                    + "; b: " + ", ".join(CASES_B))
    ap.add_argument("--jobs", type=int, default=2, help="parallel processes (default 2)")
    ap.add_argument("--keep", metavar="DIR", help="keep the CSVs (and identify's JSON beside each) in DIR")
    ap.add_argument("--zoh-delay", type=float, default=None, metavar="SAMPLES",
                    help="pass --zoh-delay to identify (default: not given; identify looks for the hold in "
                         "the CSV). 0.5 is this loop's true timing")
    args = ap.parse_args(argv)
    sim_cases = SIMS[args.sim]["cases"]
    for c in args.case or ():
        if c not in sim_cases:
            ap.error(f"--case {c}: not a case of simulation {args.sim} ({', '.join(sim_cases)})")
    seeds: list[int] = []
    for part in args.seeds.split(","):
        a, _, b = part.partition("-")
        seeds += list(range(int(a), int(b or a) + 1))
    cases = args.case or list(sim_cases)
    tmp = None
    if args.keep:
        folder = Path(args.keep)
        folder.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="ident_unmodelled_")
        folder = Path(tmp.name)
    jobs = [(c, s, str(folder), args.zoh_delay, args.sim) for c in cases for s in seeds]
    t0 = time.perf_counter()
    with Pool(max(1, args.jobs)) as pool:
        rows = []
        for r in pool.imap(run_one, jobs):
            rows.append(r)
            print(f"{r['case']:>16} seed {r['seed']}: {r['outcome']:<11} {r.get('detail', '')}  "
                  f"[sim {r['sim_s']:.1f} s, identify {r['identify_s']:.1f} s]", flush=True)
    print(f"\n{len(rows)} records in {time.perf_counter() - t0:.0f} s ({args.jobs} jobs)\n")
    print(table(rows, cases, seeds, args.sim))
    for r in rows:
        if r["outcome"] == "error":
            print(f"\n{r['case']} seed {r['seed']}: identify failed:\n{r['stderr'].rstrip()}")
    if tmp is not None:
        tmp.cleanup()
    return 1 if any(r["outcome"] == "error" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
