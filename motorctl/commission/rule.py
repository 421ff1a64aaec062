"""The commissioning rule's constants, stated once: the margins every law's gains must
hold, the closed-loop verdicts of a run, the search's budgets and the measurement's excitation
(:mod:`motorctl.commission.autotune` describes the procedure)."""

from __future__ import annotations

from dataclasses import dataclass


# ---------------------------------------------------------------- the rule (stated once)
GM_MIN_DB = 6.0          #: gain margin ≥ [dB] (default of :class:`Rule`)
PM_MIN_DEG = 10.0        #: phase margin ≥ [deg]
MS_MAX_DB = 16.0         #: peak sensitivity ≤ [dB] (|S| ≤ 6.3)
FRF_SIGMAS = 4.0         #: the rule takes a measured line where it departs from the fitted model by more than this
                         #: many times its random error (:func:`motorctl.commission.choose.loop_frf`)
COH_USED = 0.5           #: the rule takes the measured FRF at lines of at least this coherence, the model elsewhere
F_TRACK_HZ = 5.0         #: where the tracking error lives (the programs' moves last ~0.5 s) [Hz]; at 2 Hz
                         #: |L| was the integral action's, and the rule ranked last the PID shapes of weak
                         #: integral that the fitted friction feed-forward allows (Y: 1.045 um against 0.785)
ZETA_RIGID = (0.15, 0.2, 0.25)   #: damping ratios the family adds on a plant the fit finds no mode in
                                 #: (:func:`motorctl.commission.choose.family_zetas`)
U_REST_FRACTION = 0.02   #: u RMS at rest ≤ this share of u_lim without a reference run (0.2 V at 10 V)
SAT_FACTOR = 1.5         #: saturated samples ≤ this factor times those of the configured controller
SAT_FLOOR_SHARE = 5e-5   #: on the same run, or of this share of the run if more (10 in 40 s at 5 kHz)
SAT_ALPHA = 0.05         #: a short run fails on saturation when its count is above this upper quantile of
                         #: a count at the full run's allowed rate (:func:`motorctl.commission.verify.limits`)
REST_SCREEN_SLACK = 1.1  #: a short run passes the screen with a predicted full-run rest noise up to this factor
                         #: above the full run's limit (the prediction scatters ~10 %; the best sits at the limit)
REST_FACTOR = 1.5        #: u RMS at rest ≤ this factor times the configured controller's on the same run
FULL_PERIODS = 10        #: the confirmation runs this many program periods (the whole program, as run)
CONFIRM_ROUNDS = 2       #: rounds of FULL_TRIES confirmations while nothing is written
FULL_TRIES = 5           #: candidates (by their short run's L2[e]) confirmed on a full run at 100 %
STEP_DOWN = (0.75, 0.65, 0.55, 0.5, 0.35)   #: the best candidate's steps down (below or instead of the confirmed)
BRACKET_RUNS = 3         #: full runs of the bracket between the confirmed gains and better-tracking failed ones
BRACKET_EXPONENT = 4.0   #: saturated samples ~ (damping gain ζω)^this until the full runs fit their own
BRACKET_EXPONENT_RANGE = (2.0, 8.0)   #: (gantry X C2, 40 s: 3.4 over ζ 0.3-0.4, 13 .. 49 samples)
BRACKET_T_SLACK = 1.1   #: the bracket's error corner ω/ζ up to this factor times the best failed candidate's
ZETA_BELOW = 5.0 / 6.0   #: the bracket also tries the family one notch of ζ below its lowest (0.3 -> 0.25)
STEP_UP = 1.25          #: the confirmed gains' step up where the margins allow; halved (in log) after a
STEP_UP_MIN = 1.05      #: failed step, down to this factor (:meth:`motorctl.commission.verify._Verification.climb`)
STEP_UP_TRIES = 3       #: steps up tried, at most
OSC_RATIO = 100.0        #: oscillation: a line in u at rest this far above its spectrum's median,
                         #: or e's spectrum this far above the configured controller's
SCALES = (0.5, 0.75, 1.0)  #: verification ladder (share of the chosen loop gain)
BACKOFF = (0.35, 0.25)     #: tried in turn when 50 % fails; the first that passes is kept
SEARCH_RUNS = 6          #: runs per shape of the search, at most
SEARCH_BUDGET = 14       #: runs of the search over all shapes of a law, at most
PRUNE_SHARE = 0.5        #: the search probes only the shapes whose quiet |L(F_TRACK_HZ)| is below this
                         #: share of that of the least L2[e] passed so far
PROBE_RUNS = 2           #: ... with this many runs, unless one passes below that L2[e]
NOISE_EXPONENT = 0.7     #: measured rest noise ~ predicted^this within a shape, until its own runs fit it
NOISE_SLACK = 1.1        #: the search still runs gains whose calibrated rest-noise prediction is
                         #: up to this factor above the level (the run judges; the prediction
                         #: grows ~6 % per ω step and the best often sits at the level itself)
REFINE_RUNS = 6          #: runs of the local refinement around the search's best, at most
RIDGE_RUNS = 5           #: runs of the walk along the margin edge from the search's best, at most
RIDGE_SPAN = 1.6         #: the walk's next point: up to this factor on the damping gain (C1/C2: k_s; PID: D)
RIDGE_POINTS = 9         #: ... among this many (:meth:`motorctl.commission.verify._Verification.ridge`)
EDGE_TOL = 0.01          #: the margin edge is bracketed to this share of the stiffness gain (log)
EDGE_SPAN = 4.0          #: ... within this factor of it either way (:func:`motorctl.commission.choose.edge_member`)
WINNER_TRIES = 3         #: search winners whose ladder is climbed before the rule's gains are kept
SATURATED = "saturated samples"   #: the words of the saturation verdict (:func:`admissible`)

# ---------------------------------------------------------------- the measurement
HOLD_HZ, HOLD_ZETA, HOLD_R = 20.0, 0.7, 5.0   #: the conservative holding PID
PERIOD_S = 1.0           #: multisine period [s] (1 Hz lines)
F_LO, F_SHAPE = 10.0, 60.0   #: lowest line, corner of the f² rise of the amplitudes [Hz]
LINE_SPACING = 0.01      #: lines every max(1 Hz, 1 % of f): 1/6 of a mode's width at ζ = 0.03
F_BOOST = 250.0          #: line amplitudes rise ∝ f² above this [Hz] (the response falls ∝ 1/f² and faster)
F_HI_SHARE = 0.48        #: highest line as a share of fs
EXC_SHARE = 0.8          #: |r| ≤ this share of u_lim
DISP_SHARE = 0.08        #: displacement RMS (catalogue model, open loop) ≤ this share of the FE limit
GUARD_SHARE = 0.5        #: |e| ≥ this share of the smallest FE limit switches the excitation off
STROKE_MARGIN = 0.1      #: the pass keeps this share of the stroke from each soft limit
REST_S = 0.6             #: rest at the start of the pass (encoder noise at rest) [s]
PERIODS = 32             #: measured multisine periods (after one ramp and one settling period)
#: the constant-velocity passes of the friction fit: speeds as shares of the top speed, each
#: one pass up and one down the stroke (steady-state force against speed, both directions)
FRICTION_SPEEDS = (1.0 / 3.0, 2.0 / 3.0, 1.0)
FRICTION_V_SHARE = 0.25  #: top pass speed ≤ this share of the axis's max velocity
FRICTION_A_SHARE = 0.25  #: pass acceleration: this share of the program's a_max, at most FRICTION_A_MAX
FRICTION_A_MAX = 5.0     #: [m/s²]
FRICTION_CRUISE = 0.6    #: the top speed keeps this share of the pass at constant velocity, at least
FRICTION_SKIP_S = 0.15   #: the window of a pass starts this long after its cruise does (the hold
                         #: PID's integrator settles on the friction step: corner ω_n/5 = 25 rad/s)



@dataclass(frozen=True)
class Rule:
    """The margins the rule demands on the measured response, at every rung of the ladder
    (gain margin ≥ gm_min_db [dB], phase margin ≥ pm_min_deg [deg], peak sensitivity ≤
    ms_max_db [dB]). The defaults are the rule's; a user may state others (``motorctl autotune
    --pm-min-deg ...``)."""

    gm_min_db: float = GM_MIN_DB
    pm_min_deg: float = PM_MIN_DEG
    ms_max_db: float = MS_MAX_DB

    def holds(self, mg) -> bool:
        return mg.meets(self.gm_min_db, self.pm_min_deg, self.ms_max_db)

    def text(self) -> str:
        return f"GM >= {self.gm_min_db:g} dB, PM >= {self.pm_min_deg:g} deg, |S| <= {self.ms_max_db:g} dB"


RULE = Rule()


class AutotuneError(ValueError):
    """The axis cannot be autotuned as configured (one line: what and why)."""
