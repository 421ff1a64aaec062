"""Simulated gantry: the physical plant of paper eq. (1)+(3) per axis behind the Driver interface.

Each ``write()`` holds the commanded voltage over one period (zero-order hold) and integrates

    M ẍ = F_m(u)·(1 + ripple(x)) − B ẋ − A_f S_f(ẋ) + F_0 + F_effects(x, ẋ, t) + F_noise

with ``substeps`` RK4 steps per period (docs/control-law.md, Plant simulation); ``read()`` returns the position quantised
to the encoder resolution (0.5 µm, the paper's Section 6). The plant advances exactly one period per
write, so a run is the same whether the loop is paced by the wall clock or a virtual clock,
and the same seed gives the same noise.

Effects the controllers' model does not have (all off by default): one key per effect family
under ``axes.NAME.driver.effects`` (cogging, force ripple, Stribeck, asymmetric and
position-dependent friction, spring, payload change, periodic disturbance), plus
``input_delay_s`` (transport delay, a fraction of a period as the mean of the delayed held input:
the input_delay family) and
``force_noise_N`` (Gaussian, held per period, seeded). Each family's options model and what it
does to the plant (:class:`motorctl.effects.base.PlantTerm`: a force F_eff [N], a factor on the
thrust, a mass change, a delayed input) live in its module ``motorctl/effects/<name>.py``; the
plant finds them through the registry :data:`motorctl.effects.FAMILIES`.

Unmodelled dynamics the paper neglects (§II; all off by default, each an option of
``axes.NAME.driver``; with all of them off the plant is bitwise the rigid one above):

* structural mode (``mode_hz`` > 0): the mass splits into the carriage (encoder, motor, friction)
  m_c = (1 − f) M and a load m_l = f M (``mode_load_fraction`` f), coupled by a spring k and a
  damper c with the free-free mode at ``mode_hz`` [Hz] and damping ratio ``mode_damping``:
  k = ω² μ, c = 2 ζ ω μ, μ = m_c m_l / M (reduced mass). The encoder reads the carriage
  (collocated), so force → y shows an antiresonance at ω √(1 − f) below the resonance at ω.
  Backlash (``backlash_m`` > 0, needs the mode): the load is held with a play of that total
  width, the coupling acts only beyond it, F_k = k·dz(x_c − x_l) + c·(ẋ_c − ẋ_l) in contact,
  0 inside the gap (dz: the dead zone of half-width ``backlash_m``/2; Nordin & Gutman,
  "Controlling mechanical systems with backlash — a survey", Automatica 38, 2002, the dead-zone
  model). No identification family models it.
* current loop (``current_loop_hz`` > 0): the motor force follows F_m(u) through a first-order
  low-pass of bandwidth ``current_loop_hz`` [Hz] (−3 dB), integrated exactly under the ZOH; and
  ``current_loop_delay_s`` [s] of transport delay before it (any value: whole periods by a delay
  line, the fraction as a switching instant inside the period).
* encoder errors (drawn once per period after integrating, seeded): Gaussian position noise of
  standard deviation ``encoder_noise_m`` and the interpolation (sub-divisional) error
  ``encoder_interpolation_m`` · sin(2π x / ``encoder_signal_period_m``), both before the
  quantisation to ``encoder_resolution_m``.

Without effect hooks, these run in a second compiled kernel (``_rk4_flex``). With hooks, a
period is one compiled call too (``_hooked_step``: the effects' terms evaluated by
:mod:`motorctl.effects.plant`) when every effect's term is compiled
(:meth:`motorctl.effects.base.PlantTerm.compiled`); a term of Python hooks only (a family
outside the project's registry) runs the general Python path (the same equations).

Homing (``home_switch_m``, ``index_pulse_m``): a home switch active at and below
``home_switch_m`` (``home_switch``), and the encoder's index pulse at ``index_pulse_m``: once
armed (:meth:`SimDriver.arm_index`), the reading at the mark is latched (``index_latch_m``)
between cycles; :meth:`SimDriver.set_position_offset` then shifts the reading (homing sets the
machine coordinates).

Stiction (``stiction_N`` > 0, Karnopp): while |ẋ| is below ``stiction_velocity_m_per_s`` and
the force applied at rest, the motor's F_m(u) (as commanded, before the current loop), F_0, the
force noise and a push, is within ``stiction_N``, the carriage (and load) is held where it was.
By default the test sees neither the effects' forces (a spring, cogging, a disturbance: held
whatever their size) nor the friction they add (the breakaway stays ``stiction_N`` where an
effect raises the kinetic friction above it, and the carriage then creeps under a force between
the two, at the speed where S_f(ẋ) times that friction balances it).
``stiction_with_effects: true`` makes the test see both: the effects' forces at rest (S_f = 0)
join the applied force, and the breakaway is ``stiction_N`` plus the friction the effects add
at rest in the direction of that force (S_f = ±1), so that static friction stays
``stiction_N`` − ``coulomb_N`` above the kinetic level along the stroke. It changes what an
effect costs at rest (docs/identification.md, §6, "The plant at rest"); it is off by default,
as the tables were measured.

Fault injection for tests (:meth:`SimDriver.inject`): read errors, NaN positions, encoder
jumps, amplifier faults and an external push force for a number of cycles.

Command watchdog (``watchdog_s`` > 0, like a real drive's: LinuxCNC hm2 ``timeout_ns``, CiA 402
0x6007, Klipper ``maximum_mcu_duration``): when no ``write`` arrives for ``watchdog_s`` of wall
time (CLOCK_MONOTONIC), the drive drops to 0 V with the amplifier off for the whole gap (the
plant coasts at 0 V over the missed periods, at most ``watchdog_max_catchup`` of them) and
reports an amplifier fault once, which the supervisor latches.
"""

from __future__ import annotations

import math
import time
from typing import Annotated

import numpy as np
from numba.experimental.structref import StructRefProxy
from pydantic import Field, model_validator

from motorctl.driver import Driver, StopCheck
from motorctl.effects import FAMILIES, effects_model
from motorctl.effects import plant as effect_terms
from motorctl.effects.input_delay import delay_line
from motorctl.jit import BundleType, borrow, bundle, copy_into, define_bundle, entry, njit
from motorctl.model import S_F_GAIN, PhysicalAxis
from motorctl.schema import NonNeg, Pos, StrictModel

_TWO_OVER_PI = 2.0 / math.pi
# the plain plant (no extra effects) is compiled: ~1 µs a period instead of ~12 µs


@njit
def _motor_force(u, a1, a2, a3):
    """F_m(u) = A1 u + A2 u|u| + A3 u³ [N] (eq. 3) under u [V], A1 [N/V], A2 [N/V²], A3 [N/V³]
    (:meth:`AxisPlant._motor_force` in the Python path: the same operations)."""
    return a1 * u + a2 * u * abs(u) + a3 * u * u * u


def _rk4_with(acc):
    """The RK4 integrator of the plant whose accelerations are ``acc(xc, vc, xl, vl, t, tau, args)``
    -> (ẍ_c, ẍ_l) [m/s²] (carriage and load at plant time t [s], tau [s] into the period; ``args``
    the variant's parameters, a tuple): ``rk4(args, xc, vc, xl, vl, t, h, n)`` takes ``n``
    classical RK4 steps of h [s] and returns xc, vc, xl, vl, t, tau.

    The one RK4 step of every plant variant: compiled (:func:`njit`, one cached kernel per
    ``acc``) for the rigid plant (:func:`_acc_rigid`, the load a copy of the carriage), the
    two-mass plant (:func:`_acc_two_mass`) and both with the effects' compiled terms
    (:func:`_acc_rigid_hooked`, :func:`_acc_two_mass_hooked`); as plain Python for a family with
    Python hooks only (:meth:`AxisPlant._step_rigid`, :meth:`AxisPlant._step_flex`). ``acc`` is
    bound in the closure, not passed as an argument: a compiled function passed as a value is
    a pointer numba cannot cache."""

    def rk4(args, xc, vc, xl, vl, t, h, n):
        tau = 0.0
        for _ in range(n):
            a1c, a1l = acc(xc, vc, xl, vl, t, tau, args)
            v2c, v2l = vc + 0.5 * h * a1c, vl + 0.5 * h * a1l
            a2c, a2l = acc(xc + 0.5 * h * vc, v2c, xl + 0.5 * h * vl, v2l, t + 0.5 * h, tau + 0.5 * h, args)
            v3c, v3l = vc + 0.5 * h * a2c, vl + 0.5 * h * a2l
            a3c, a3l = acc(xc + 0.5 * h * v2c, v3c, xl + 0.5 * h * v2l, v3l, t + 0.5 * h, tau + 0.5 * h, args)
            v4c, v4l = vc + h * a3c, vl + h * a3l
            a4c, a4l = acc(xc + h * v3c, v4c, xl + h * v3l, v4l, t + h, tau + h, args)
            xc += h / 6.0 * (vc + 2.0 * v2c + 2.0 * v3c + v4c)
            xl += h / 6.0 * (vl + 2.0 * v2l + 2.0 * v3l + v4l)
            vc += h / 6.0 * (a1c + 2.0 * a2c + 2.0 * a3c + a4c)
            vl += h / 6.0 * (a1l + 2.0 * a2l + 2.0 * a3l + a4l)
            t += h
            tau += h
        return xc, vc, xl, vl, t, tau

    return rk4


@njit
def _acc_rigid(x, v, xl, vl, t, tau, args):
    """:func:`_rk4_with`'s accelerations of the rigid plant, eq. (1) with smooth Coulomb friction;
    ``args`` = (F_m(u) [N], M [kg], B, A_f, F_0, F_noise, F_ext); the same operations in the
    same order as :meth:`AxisPlant._acc` without effects."""
    fm, m, b, fc, f0, f_noise, f_ext = args
    sf = _TWO_OVER_PI * math.atan(S_F_GAIN * v)
    a = (fm - b * v - fc * sf + f0 + f_noise + f_ext) / m
    return a, a


_rk4_rigid = njit(_rk4_with(_acc_rigid))


@njit
def _rk4_plain(x, v, t, u, h, n, m, a1, a2, a3, b, fc, f0, f_noise, f_ext):
    """``n`` RK4 steps of eq. (1) with the force curve of eq. (3) and smooth Coulomb friction
    (:func:`_rk4_with` of :func:`_acc_rigid`). Returns x, v, t."""
    x, v, _, _, t, _ = _rk4_rigid((_motor_force(u, a1, a2, a3), m, b, fc, f0, f_noise, f_ext),
                                  x, v, 0.0, 0.0, t, h, n)
    return x, v, t


@njit
def _force_at(tau, f_start, f_prev, f_cur, delta, tau_i):
    """Motor force [N] at time ``tau`` [s] into the period: the command is ``f_prev`` before
    ``delta`` [s] and ``f_cur`` after it; first-order lag of time constant ``tau_i`` [s] (0: none)
    starting from ``f_start`` (exact solution under the piecewise-constant command)."""
    if tau_i <= 0.0:
        return f_prev if tau < delta else f_cur
    if tau < delta:
        return f_prev + (f_start - f_prev) * math.exp(-tau / tau_i)
    fd = f_prev + (f_start - f_prev) * math.exp(-delta / tau_i)
    return f_cur + (fd - f_cur) * math.exp(-(tau - delta) / tau_i)


@njit
def _coupling(dx, dv, ks, cs, half_gap):
    """The force [N] the carriage applies to the load through the mode's spring k [N/m] and
    damper c [N s/m] at deflection dx = x_c − x_l [m], dv = ẋ_c − ẋ_l [m/s], with a play of
    half-width ``half_gap`` [m] (0: none): k·dz(dx) + c·dv in contact, 0 inside the play."""
    if half_gap <= 0.0:
        return ks * dx + cs * dv
    if dx > half_gap:
        return ks * (dx - half_gap) + cs * dv
    if dx < -half_gap:
        return ks * (dx + half_gap) + cs * dv
    return 0.0


@njit
def _acc_flex(fm, x1, v1, x2, v2, mc, ml, ks, cs, b, fc, f0, f_noise, f_ext, half_gap):
    """Accelerations [m/s²] of carriage and load under motor force fm [N] (``ml`` = 0: rigid;
    ``half_gap`` [m]: the coupling's play, :func:`_coupling`)."""
    sf = _TWO_OVER_PI * math.atan(S_F_GAIN * v1)
    f = fm - b * v1 - fc * sf + f0 + f_noise + f_ext
    if ml > 0.0:
        fsp = _coupling(x1 - x2, v1 - v2, ks, cs, half_gap)
        return (f - fsp) / mc, fsp / ml
    a = f / mc
    return a, a


@njit
def _acc_two_mass(xc, vc, xl, vl, t, tau, args):
    """:func:`_rk4_with`'s accelerations of the two-mass plant under the motor force of
    :func:`_force_at`; ``args`` = (f_start, f_prev, f_cur, delta, tau_i, m_c, m_l, k, c, B, A_f,
    F_0, F_noise, F_ext, half the play [m])."""
    f_start, f_prev, f_cur, delta, tau_i, mc, ml, ks, cs, b, fc, f0, f_noise, f_ext, half_gap = args
    fm = _force_at(tau, f_start, f_prev, f_cur, delta, tau_i)
    return _acc_flex(fm, xc, vc, xl, vl, mc, ml, ks, cs, b, fc, f0, f_noise, f_ext, half_gap)


_rk4_two_mass = njit(_rk4_with(_acc_two_mass))


@njit
def _rk4_flex(xc, vc, xl, vl, t, f_start, f_prev, f_cur, delta, tau_i, h, n, mc, ml, ks, cs,
              b, fc, f0, f_noise, f_ext, half_gap):
    """``n`` RK4 steps of the two-mass plant (carriage xc, vc; load xl, vl) with the motor force
    of :func:`_force_at`; ``ml`` = 0 means no structural mode (one rigid mass ``mc``); the
    coupling's play of half-width ``half_gap`` [m] (:func:`_coupling`). Returns xc, vc, xl, vl, t
    and the force at the end of the period."""
    xc, vc, xl, vl, t, tau = _rk4_two_mass((f_start, f_prev, f_cur, delta, tau_i, mc, ml, ks, cs, b, fc, f0,
                                             f_noise, f_ext, half_gap), xc, vc, xl, vl, t, h, n)
    return xc, vc, xl, vl, t, _force_at(tau, f_start, f_prev, f_cur, delta, tau_i)


#: ``axes.NAME.driver.effects``: one optional key per simulated effect family (the registry's
#: families with ``sim_options``, e.g. ``cogging: {amplitudes_N: [...], period_m: ...}``).
Effects = effects_model(__name__)


class SimAxisOptions(StrictModel):
    """Per-axis plant (YAML ``axes.NAME.driver``); SI units, paper eq. (1) and (3)."""

    mass_kg: Pos
    a1_N_per_V: Pos
    a2_N_per_V2: float = 0.0
    a3_N_per_V3: float = 0.0
    viscous_N_s_per_m: NonNeg = 0.0
    coulomb_N: NonNeg = 0.0
    offset_N: float = 0.0
    initial_position_m: float = 0.0
    # homing inputs (module docstring, "Homing"): a home switch active at and below this
    # position, and the encoder's index pulse at that one [m]; None: none
    home_switch_m: float | None = None
    index_pulse_m: float | None = None
    encoder_resolution_m: Pos = 0.5e-6
    input_delay_s: Annotated[float, Field(ge=0.0, le=0.1)] = 0.0     # transport delay [s]
    force_noise_N: Annotated[float, Field(ge=0.0, le=1e4)] = 0.0    # force noise, std [N]
    effects: Effects = Effects()
    # unmodelled dynamics (module docstring; 0 = off)
    mode_hz: Annotated[float, Field(ge=0.0, le=1e5)] = 0.0   # structural mode, free-free [Hz]
    mode_damping: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.02   # its damping ratio [-]
    mode_load_fraction: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.3  # m_l / M [-]
    backlash_m: Annotated[float, Field(ge=0.0, le=0.01)] = 0.0   # play of the load's coupling [m]
    current_loop_hz: Annotated[float, Field(ge=0.0, le=1e6)] = 0.0   # current-loop bandwidth [Hz]
    current_loop_delay_s: Annotated[float, Field(ge=0.0, le=0.1)] = 0.0  # delay before it [s]
    encoder_noise_m: Annotated[float, Field(ge=0.0, le=0.01)] = 0.0  # position noise, std [m]
    encoder_interpolation_m: Annotated[float, Field(ge=0.0, le=0.01)] = 0.0  # interpolation error [m]
    encoder_signal_period_m: Pos = 20e-6     # scale (signal) period of the interpolation error [m]
    # stiction (Karnopp): a carriage at rest stays at rest while the applied force is below
    # the breakaway force (the smooth Coulomb term S_f cannot hold a disabled axis still)
    stiction_N: Annotated[float, Field(ge=0.0, le=1e5)] = 0.0    # breakaway force [N]; 0 = off
    stiction_velocity_m_per_s: Annotated[float, Field(gt=0.0, le=0.1)] = 1e-4  # "at rest" below [m/s]
    # the Karnopp test sees the effects (module docstring, "Stiction"): their forces at rest in
    # the applied force, and the breakaway kept stiction_N - coulomb_N above the kinetic friction
    # they set at rest; off: the motor, offset, noise and push against stiction_N only
    stiction_with_effects: bool = False

    @model_validator(mode="after")
    def _backlash_needs_mode(self):
        if self.backlash_m > 0.0 and self.mode_hz <= 0.0:
            raise ValueError(f"backlash_m = {self.backlash_m:g}: the play is in the coupling of the load, "
                             "which needs mode_hz > 0 (the structural mode's spring)")
        return self

    def flexible(self) -> bool:
        """True when a structural mode or an amplifier current loop / delay is switched on."""
        return self.mode_hz > 0.0 or self.current_loop_hz > 0.0 or self.current_loop_delay_s > 0.0

    def mode_coefficients(self) -> tuple[float, float, float, float]:
        """(m_c [kg], m_l [kg], k [N/m], c [N s/m]) of the structural mode; m_l = k = c = 0
        when it is off."""
        if self.mode_hz <= 0.0:
            return self.mass_kg, 0.0, 0.0, 0.0
        f = self.mode_load_fraction
        mc, ml = (1.0 - f) * self.mass_kg, f * self.mass_kg
        mu = mc * ml / self.mass_kg
        w = 2.0 * math.pi * self.mode_hz
        return mc, ml, w * w * mu, 2.0 * self.mode_damping * w * mu

    def physical(self) -> PhysicalAxis:
        return PhysicalAxis(self.mass_kg, self.a1_N_per_V, self.a2_N_per_V2, self.a3_N_per_V3,
                            self.viscous_N_s_per_m, self.coulomb_N, self.offset_N)


_UNMODELLED = ("mode_hz", "mode_damping", "mode_load_fraction", "backlash_m", "current_loop_hz",
               "current_loop_delay_s", "encoder_noise_m", "encoder_interpolation_m",
               "encoder_signal_period_m")


class SimOptions(StrictModel):
    """Driver-level options (YAML ``driver:``)."""

    seed: int = 0
    substeps: Annotated[int, Field(ge=1, le=100)] = 4
    watchdog_s: NonNeg = 0.0          # 0 = no command watchdog (virtual clock runs)
    watchdog_max_catchup: Annotated[int, Field(ge=0)] = 5000


# the compiled plant (an axis without effect hooks): its state and parameters, by name
(PS_X, PS_XD, PS_XL, PS_VL, PS_T, PS_F, PS_FPREV, PS_FNOISE, PS_FEXT, PS_ENC, PS_DLI, PS_NZI) = range(12)
N_PS = 12
#: normal draws taken from a plant's Generator at a time (even: a period takes 0, 1 or 2)
NOISE_BLOCK = 256
(PP_M, PP_A1, PP_A2, PP_A3, PP_B, PP_FC, PP_F0, PP_NOISE, PP_STIC, PP_STICKV, PP_H, PP_N, PP_MC,
 PP_ML, PP_KS, PP_CS, PP_TAUI, PP_DELTA, PP_ENCSIG, PP_FLEX, PP_Q, PP_ENCAMP, PP_ENCK, PP_NDL,
 PP_STICFX, PP_GAP) = range(26)
N_PP = 26
# the simulated driver's injected faults (SimDriver.inject): cycles left per axis
INJ_READ, INJ_NAN, INJ_AMP, INJ_PUSH = range(4)


@njit
def _plant_step(u, s, p, dl, nz):
    """One period of an axis without effect hooks under u [V] (:meth:`AxisPlant.step`): force
    noise, Karnopp stiction, the rigid plant (:func:`_rk4_plain`) or the structural mode and
    current loop (:func:`_rk4_flex`, with the current loop's whole-period delay line ``dl``),
    encoder noise; the same operations in the same order. The noise: the next normal draws of
    the plant's Generator, taken a block ``nz`` at a time (the same values, in the same order,
    as one draw at a time); s[PS_NZI] is the next unused one."""
    a1, a2, a3 = p[PP_A1], p[PP_A2], p[PP_A3]
    rest, x0, xl0 = _period_begin(u, s, p, nz)
    stuck = rest and _held(u, s, p)
    n = int(p[PP_N])
    if p[PP_FLEX] == 0.0:
        s[PS_X], s[PS_XD], s[PS_T] = _rk4_plain(s[PS_X], s[PS_XD], s[PS_T], u, p[PP_H], n, p[PP_M], a1, a2,
                                                a3, p[PP_B], p[PP_FC], p[PP_F0], s[PS_FNOISE], s[PS_FEXT])
    else:
        f_prev, f_cur = _current_command(u, s, p, dl)
        (s[PS_X], s[PS_XD], s[PS_XL], s[PS_VL], s[PS_T], s[PS_F]) = _rk4_flex(
            s[PS_X], s[PS_XD], s[PS_XL], s[PS_VL], s[PS_T], s[PS_F], f_prev, f_cur, p[PP_DELTA], p[PP_TAUI],
            p[PP_H], n, p[PP_MC], p[PP_ML], p[PP_KS], p[PP_CS], p[PP_B], p[PP_FC], p[PP_F0], s[PS_FNOISE],
            s[PS_FEXT], p[PP_GAP])
    _period_end(s, p, nz, stuck, x0, xl0)


@njit
def _period_begin(u, s, p, nz):
    """The start of a period (:func:`_plant_step`, :func:`_hooked_step`): the force noise's draw.
    Returns (at rest: stiction on and |ẋ| within its band, x, x_load) before the period."""
    if p[PP_NOISE] > 0.0:
        j = int(s[PS_NZI])
        s[PS_NZI] = j + 1
        s[PS_FNOISE] = p[PP_NOISE] * nz[j]
    return p[PP_STIC] > 0.0 and abs(s[PS_XD]) < p[PP_STICKV], s[PS_X], s[PS_XL]


@njit
def _held(u, s, p):
    """Karnopp stiction, for a carriage at rest: is it held under u [V] this period, the force
    applied at rest (motor, offset, noise, push) within the breakaway F_s?"""
    f = _motor_force(u, p[PP_A1], p[PP_A2], p[PP_A3]) + p[PP_F0] + s[PS_FNOISE] + s[PS_FEXT]
    return abs(f) <= p[PP_STIC]


@njit
def _current_command(u, s, p, dl):
    """The current loop's force commands of the flexible plant: (the last period's, this
    period's after the whole-period delay line ``dl``) [N]."""
    f_cur = _motor_force(u, p[PP_A1], p[PP_A2], p[PP_A3])
    m = dl.shape[0]
    if m > 0:
        i = int(s[PS_DLI])
        out = dl[i]
        dl[i] = f_cur
        s[PS_DLI] = (i + 1) % m
        f_cur = out
    f_prev = s[PS_FPREV]
    s[PS_FPREV] = f_cur
    return f_prev, f_cur


@njit
def _period_end(s, p, nz, stuck, x0, xl0):
    """The end of a period: a stuck carriage (and load) held where it was, the encoder noise's
    draw."""
    if stuck:
        s[PS_X] = x0
        s[PS_XD] = 0.0
        s[PS_XL] = xl0
        s[PS_VL] = 0.0
    if p[PP_ENCSIG] > 0.0:
        j = int(s[PS_NZI])
        s[PS_NZI] = j + 1
        s[PS_ENC] = p[PP_ENCSIG] * nz[j]


@njit
def _plant_measured(s, p):
    """Encoder reading [m] (:meth:`AxisPlant.measured`)."""
    q = p[PP_Q]
    if p[PP_ENCAMP] > 0.0 or p[PP_ENCSIG] > 0.0:
        x = s[PS_X] + p[PP_ENCAMP] * math.sin(p[PP_ENCK] * s[PS_X]) + s[PS_ENC]
        return q * np.rint(x / q)
    return q * np.rint(s[PS_X] / q)


#: the fields of :class:`SimIO`, in constructor order
SIM_FIELDS = ("pos", "read_error", "amp_fault", "amp_enabled", "applied_u", "S", "P", "DL", "NZ", "inj", "jump",
              "push", "TC", "TT", "TL", "NT", "u_cmd", "en_cmd", "true_pos")


class SimIOType(BundleType):
    """numba type of :class:`SimIO`."""


class SimIO(StructRefProxy):
    """The arrays of the simulated driver's exchange by name (:data:`SIM_FIELDS`): the reading
    (pos [m], read_error, amp_fault: (n,)), the amplifier (amp_enabled, applied_u [V]: (n,)), the
    compiled plants' rows (S, P, DL, NZ: one row per axis), the injected faults (inj: (n, 4)
    cycles left, jump [m], push [N]: (n,)), the plants' compiled effect terms (NT (n,) how many,
    0 for none; TC (n, m) codes, TT (n, m, w) rows, TL (n, m) lengths: each plant's
    :func:`motorctl.effects.plant.rows`, zero-padded), the command the write applies (u_cmd [V],
    en_cmd: (n,); the loop's own output arrays once the driver has checked them, so that a
    cycle's write passes no array from Python: numba allocates a wrapper for each array it
    unboxes), the carriages' true positions at the read (true_pos [m]: (n,)); passed to the
    compiled read and write as one argument (:func:`motorctl.jit.bundle`)."""


define_bundle(SimIOType, SimIO, SIM_FIELDS)


@njit
def _make_sim_io(pos, read_error, amp_fault, amp_enabled, applied_u, S, P, DL, NZ, inj, jump, push, TC, TT, TL, NT,
                 u_cmd, en_cmd, true_pos):
    return SimIO(pos, read_error, amp_fault, amp_enabled, applied_u, S, P, DL, NZ, inj, jump, push, TC, TT, TL, NT,
                 u_cmd, en_cmd, true_pos)


@njit
def _sim_read(io, bitten):
    """:meth:`SimDriver.read` of every axis on the :class:`SimIO` ``io``: injected read errors,
    NaN readings and amplifier faults, else the encoder reading plus an injected jump [m]; and,
    whatever the encoder does, each carriage's true position (io.true_pos [m])."""
    # borrowed views (motorctl.jit.borrow): the bundle holds the arrays through the call
    pos, read_error, amp_fault = borrow(io.pos), borrow(io.read_error), borrow(io.amp_fault)
    S, P, inj, jump, true_pos = borrow(io.S), borrow(io.P), borrow(io.inj), borrow(io.jump), borrow(io.true_pos)
    for i in range(pos.shape[0]):
        true_pos[i] = S[i, PS_X]
        if inj[i, INJ_READ] > 0:
            inj[i, INJ_READ] -= 1
            read_error[i] = True
            if bitten:
                amp_fault[i] = True
            continue
        read_error[i] = False
        if inj[i, INJ_NAN] > 0:
            inj[i, INJ_NAN] -= 1
            pos[i] = math.nan
            if bitten:
                amp_fault[i] = True
            continue
        pos[i] = _plant_measured(borrow(S[i]), borrow(P[i])) + jump[i]
        amp_fault[i] = inj[i, INJ_AMP] > 0 or bitten
        if inj[i, INJ_AMP] > 0:
            inj[i, INJ_AMP] -= 1


@njit
def _sim_write(io, bitten):
    """:meth:`SimDriver.write` of every axis (each plant's whole period compiled) on the
    :class:`SimIO` ``io``: the amplifier's enable and output (NaN never reaches it), an injected
    push, one period of each plant (:func:`_plant_step`, or :func:`_hooked_step` with the
    plant's effect terms), under the command io.u_cmd [V], io.en_cmd (n,). Returns how many
    plants have used up their block of noise draws (to be refilled before the next period)."""
    # borrowed views (motorctl.jit.borrow): the bundle holds the arrays through the call
    u_v, enable, amp_fault = borrow(io.u_cmd), borrow(io.en_cmd), borrow(io.amp_fault)
    amp_enabled, applied_u, inj, push = borrow(io.amp_enabled), borrow(io.applied_u), borrow(io.inj), borrow(io.push)
    S, P, DL, NZ = borrow(io.S), borrow(io.P), borrow(io.DL), borrow(io.NZ)
    TC, TT, TL, NT = borrow(io.TC), borrow(io.TT), borrow(io.TL), borrow(io.NT)
    need = 0
    for i in range(u_v.shape[0]):
        on = enable[i] and not amp_fault[i] and not bitten
        amp_enabled[i] = on
        u = u_v[i] if on else 0.0
        if u != u:
            u = 0.0
        applied_u[i] = u
        if inj[i, INJ_PUSH] > 0:
            inj[i, INJ_PUSH] -= 1
            S[i, PS_FEXT] = push[i]
        else:
            S[i, PS_FEXT] = 0.0
        k = NT[i]
        s, p, dl, nz = borrow(S[i]), borrow(P[i]), borrow(DL[i, :int(P[i, PP_NDL])]), borrow(NZ[i])
        if k > 0:
            _hooked_step(u, s, p, dl, nz, borrow(TC[i, :k]), borrow(TT[i, :k]), borrow(TL[i, :k]))
        else:
            _plant_step(u, s, p, dl, nz)
        if S[i, PS_NZI] >= NOISE_BLOCK:
            need += 1
    return need


@njit
def _sim_refresh(io, scratch):
    """:meth:`SimDriver.rehearse`'s first step: ``scratch`` (a :class:`SimIO` of copies) set to
    ``io``; the driver's own compiled read and write then run on it (their very entries, so
    that their machine code is the code warmed); ``io`` is not written."""
    copy_into(scratch.pos, io.pos)
    copy_into(scratch.read_error, io.read_error)
    copy_into(scratch.amp_fault, io.amp_fault)
    copy_into(scratch.amp_enabled, io.amp_enabled)
    copy_into(scratch.applied_u, io.applied_u)
    copy_into(scratch.S, io.S)
    copy_into(scratch.P, io.P)
    copy_into(scratch.DL, io.DL)
    copy_into(scratch.NZ, io.NZ)
    copy_into(scratch.inj, io.inj)
    copy_into(scratch.jump, io.jump)
    copy_into(scratch.push, io.push)
    copy_into(scratch.TC, io.TC)
    copy_into(scratch.TT, io.TT)
    copy_into(scratch.TL, io.TL)
    copy_into(scratch.NT, io.NT)
    copy_into(scratch.u_cmd, io.u_cmd)
    copy_into(scratch.en_cmd, io.en_cmd)
    copy_into(scratch.true_pos, io.true_pos)


@njit
def _acc_hooked(fm, x, v, t, m, b, fc, f0, f_noise, f_ext, codes, table, lengths):
    """ẍ [m/s²] of the rigid plant with the effects' compiled terms: :meth:`AxisPlant._acc` from
    the motor force fm = F_m(u) [N] on (the same operations in the same order)."""
    fm = effect_terms.thrust(fm, x, t, codes, table, lengths)
    sf = _TWO_OVER_PI * math.atan(S_F_GAIN * v)
    f = fm - b * v - fc * sf + f0 + f_noise + f_ext
    f = effect_terms.force(f, x, v, t, sf, codes, table, lengths)
    return f / effect_terms.mass(m, t, codes, table, lengths)


@njit
def _acc_rigid_hooked(x, v, xl, vl, t, tau, args):
    """:func:`_rk4_with`'s accelerations of the rigid plant with the effects' compiled terms;
    ``args`` = (F_m(u) [N], M, B, A_f, F_0, F_noise, F_ext, codes, table, lengths)."""
    fm, m, b, fc, f0, f_noise, f_ext, codes, table, lengths = args
    a = _acc_hooked(fm, x, v, t, m, b, fc, f0, f_noise, f_ext, codes, table, lengths)
    return a, a


_rk4_rigid_hooked = njit(_rk4_with(_acc_rigid_hooked))


@njit
def _acc_flex_hooked(fm, xc, vc, xl, vl, t, mc, ml0, m_tot, ks, cs, b, fc, f0, f_noise, f_ext, codes,
                     table, lengths, half_gap):
    """Accelerations [m/s²] of carriage and load under motor force fm [N] with the effects'
    compiled terms (a mass change is the load's); the general path's ``acc`` in
    :meth:`AxisPlant._step_flex` (the same operations in the same order)."""
    fm = effect_terms.thrust(fm, xc, t, codes, table, lengths)
    sf = _TWO_OVER_PI * math.atan(S_F_GAIN * vc)
    f = fm - b * vc - fc * sf + f0 + f_noise + f_ext
    f = effect_terms.force(f, xc, vc, t, sf, codes, table, lengths)
    m = effect_terms.mass(m_tot, t, codes, table, lengths)
    if ml0 > 0.0:
        fsp = _coupling(xc - xl, vc - vl, ks, cs, half_gap)
        ac = (f - fsp) / mc
        return ac, fsp / (ml0 + m - m_tot)
    ac = f / m
    return ac, ac


@njit
def _acc_two_mass_hooked(xc, vc, xl, vl, t, tau, args):
    """:func:`_rk4_with`'s accelerations of the two-mass plant with the effects' compiled terms
    (:func:`_acc_flex_hooked`); ``args`` = (f_start, f_prev, f_cur, delta, tau_i, m_c, m_l, M, k,
    c, B, A_f, F_0, F_noise, F_ext, codes, table, lengths, half the play [m])."""
    (f_start, f_prev, f_cur, delta, tau_i, mc, ml, m_tot, ks, cs, b, fc, f0, f_noise, f_ext, codes, table,
     lengths, half_gap) = args
    return _acc_flex_hooked(_force_at(tau, f_start, f_prev, f_cur, delta, tau_i), xc, vc, xl, vl, t, mc, ml,
                            m_tot, ks, cs, b, fc, f0, f_noise, f_ext, codes, table, lengths, half_gap)


_rk4_two_mass_hooked = njit(_rk4_with(_acc_two_mass_hooked))


#: the velocity [m/s] at which the effects' friction at rest is evaluated: the sign of a
#: breakaway's direction, too small for any viscous or Stribeck term to see
V_AT_REST = 1e-12


@njit
def _held_hooked(u, s, p, codes, table, lengths):
    """Karnopp stiction with the effects' terms (``stiction_with_effects``; its Python twin
    :meth:`AxisPlant._held_hooked`), for a carriage at rest: is it held under u [V] this period?
    The force applied at rest is the motor's (after the thrust terms), the offset, noise and
    push, and the effects' forces at rest (S_f = 0: a spring, cogging, a disturbance). The
    breakaway is F_s plus the friction the effects add at rest in the direction of that force
    (S_f = ±1): static friction stays F_s − F_c above the kinetic level wherever an effect
    moves it."""
    x, t = s[PS_X], s[PS_T]
    fm = effect_terms.thrust(_motor_force(u, p[PP_A1], p[PP_A2], p[PP_A3]), x, t, codes, table, lengths)
    f = effect_terms.force(fm + p[PP_F0] + s[PS_FNOISE] + s[PS_FEXT], x, 0.0, t, 0.0, codes, table, lengths)
    d = 1.0 if f >= 0.0 else -1.0
    v = d * V_AT_REST
    extra = -d * (effect_terms.force(0.0, x, v, t, d, codes, table, lengths)
                  - effect_terms.force(0.0, x, v, t, 0.0, codes, table, lengths))
    return abs(f) <= p[PP_STIC] + extra


@njit
def _hooked_step(u, s, p, dl, nz, codes, table, lengths):
    """One period of an axis whose effects all have compiled terms (:meth:`AxisPlant.step` after
    its input hooks), ``codes``/``table``/``lengths`` from :func:`motorctl.effects.plant.rows`:
    :func:`_plant_step` with :func:`_acc_rigid_hooked` / :func:`_acc_two_mass_hooked` in :func:`_rk4_with`
    (the same operations in the same order as the Python path)."""
    a1, a2, a3 = p[PP_A1], p[PP_A2], p[PP_A3]
    rest, x0, xl0 = _period_begin(u, s, p, nz)
    if p[PP_STICFX] > 0.0:
        stuck = rest and _held_hooked(u, s, p, codes, table, lengths)
    else:
        stuck = rest and _held(u, s, p)
    n = int(p[PP_N])
    if p[PP_FLEX] == 0.0:
        s[PS_X], s[PS_XD], _, _, s[PS_T], _ = _rk4_rigid_hooked(
            (_motor_force(u, a1, a2, a3), p[PP_M], p[PP_B], p[PP_FC], p[PP_F0], s[PS_FNOISE],
                                s[PS_FEXT], codes, table, lengths), s[PS_X], s[PS_XD], 0.0, 0.0, s[PS_T], p[PP_H], n)
    else:
        f_prev, f_cur = _current_command(u, s, p, dl)
        f_start = s[PS_F]
        (s[PS_X], s[PS_XD], s[PS_XL], s[PS_VL], s[PS_T], tau) = _rk4_two_mass_hooked(
            (f_start, f_prev, f_cur, p[PP_DELTA], p[PP_TAUI], p[PP_MC], p[PP_ML], p[PP_M],
                                   p[PP_KS], p[PP_CS], p[PP_B], p[PP_FC], p[PP_F0], s[PS_FNOISE], s[PS_FEXT], codes,
                                   table, lengths, p[PP_GAP]),
            s[PS_X], s[PS_XD], s[PS_XL], s[PS_VL], s[PS_T], p[PP_H], n)
        s[PS_F] = _force_at(tau, f_start, f_prev, f_cur, p[PP_DELTA], p[PP_TAUI])
    _period_end(s, p, nz, stuck, x0, xl0)


def _state_property(j: int, doc: str):
    return property(lambda self: float(self._s[j]), lambda self, v: self._s.__setitem__(j, v), doc=doc)


class AxisPlant:
    """One simulated axis. ``step(u, dt)`` integrates one ZOH period; pure floats, no arrays."""

    x = _state_property(PS_X, "carriage position [m]")
    xd = _state_property(PS_XD, "carriage velocity [m/s]")
    xl = _state_property(PS_XL, "load position [m]")
    vl = _state_property(PS_VL, "load velocity [m/s]")
    t = _state_property(PS_T, "plant time [s]")
    F = _state_property(PS_F, "motor force at the end of the last period [N]")
    f_prev = _state_property(PS_FPREV, "force command of the last period [N] (fractional delay)")
    f_noise = _state_property(PS_FNOISE, "force noise of this period [N]")
    f_ext = _state_property(PS_FEXT, "external force [N] (fault injection: a push)")
    enc_noise = _state_property(PS_ENC, "encoder noise of this period [m]")

    def __init__(self, opt: SimAxisOptions, period_s: float, rng: np.random.Generator, substeps: int):
        self.opt = opt
        self._s = np.zeros(N_PS)          # the state (PS_*), read and written by the properties above
        self.x = float(opt.initial_position_m)
        self.xd = 0.0
        self.t = 0.0
        self.m = opt.mass_kg
        self.a1, self.a2, self.a3 = opt.a1_N_per_V, opt.a2_N_per_V2, opt.a3_N_per_V3
        self.b = opt.viscous_N_s_per_m
        self.fc = opt.coulomb_N
        self.f0 = opt.offset_N
        self.q = opt.encoder_resolution_m
        self.substeps = substeps
        self.h = period_s / substeps
        self.rng = rng
        self.noise = opt.force_noise_N
        self.f_noise = 0.0
        self.f_ext = 0.0   # external force [N] (fault injection: a push)
        self.stiction = opt.stiction_N
        self.stick_v = opt.stiction_velocity_m_per_s
        self.stiction_fx = opt.stiction_with_effects
        # the effects switched on, in registry order (motorctl.effects.FAMILIES)
        terms = []
        for fam in FAMILIES.values():
            cfg = fam.sim_config(opt)
            term = fam.plant_term(cfg, period_s) if cfg is not None else None
            if term is not None:
                terms.append(term)
        self._thrust = tuple(t.thrust for t in terms if t.thrust is not None)
        self._forces = tuple(t.force for t in terms if t.force is not None)
        self._masses = tuple(t.mass for t in terms if t.mass is not None)
        self._inputs = tuple(t.input for t in terms if t.input is not None)
        # no position/time-dependent effect: the compiled plain integrator applies
        self._hooks = bool(self._thrust or self._forces or self._masses)
        # every effect term compiled: the whole period is one compiled call (_hooked_step)
        self._terms = effect_terms.rows(terms) if self._hooks else None
        self._flex = opt.flexible()
        self._plain = not (self._hooks or self._flex)
        # unmodelled dynamics (module docstring)
        self.mc, self.ml, self.ks, self.cs = opt.mode_coefficients()
        self.half_gap = 0.5 * opt.backlash_m   # the load's play, half-width [m]
        self.xl, self.vl = self.x, 0.0     # load position [m] and velocity [m/s]
        self.tau_i = 1.0 / (2.0 * math.pi * opt.current_loop_hz) if opt.current_loop_hz > 0 else 0.0
        n_del = int(math.floor(opt.current_loop_delay_s / period_s + 1e-9))
        self.delta = max(0.0, opt.current_loop_delay_s - n_del * period_s)
        self._fdelay = delay_line(n_del) if n_del > 0 else None
        self.F = 0.0          # motor force at the end of the last period [N]
        self.f_prev = 0.0     # force command of the last period [N] (fractional delay)
        self.period_s = period_s
        self.enc_sigma = opt.encoder_noise_m
        self.enc_amp = opt.encoder_interpolation_m
        self.enc_k = 2.0 * math.pi / opt.encoder_signal_period_m
        self.enc_noise = 0.0
        if self._flex and not self._hooks:
            _rk4_flex(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.tau_i, self.h, 1,
                      self.mc, self.ml, self.ks, self.cs, self.b, self.fc, self.f0, 0.0, 0.0, self.half_gap)
        if self._plain:
            _rk4_plain(0.0, 0.0, 0.0, 0.0, self.h, 1, self.m, self.a1, self.a2, self.a3, self.b,
                       self.fc, self.f0, 0.0, 0.0)   # compile (or load the cache) now
        # without effect hooks the whole period is one compiled call (_plant_step)
        self._compiled = not (self._hooks or self._inputs)
        # ... and with compiled effect terms and no input transform, one call of _hooked_step
        self.period_compiled = self._compiled or (self._terms is not None and not self._inputs)
        n_dl = n_del if self._flex else 0
        self._p = np.array([self.m, self.a1, self.a2, self.a3, self.b, self.fc, self.f0, self.noise,
                            self.stiction, self.stick_v, self.h, self.substeps, self.mc, self.ml, self.ks,
                            self.cs, self.tau_i, self.delta, self.enc_sigma, 1.0 if self._flex else 0.0,
                            self.q, self.enc_amp, self.enc_k, n_dl, 1.0 if self.stiction_fx else 0.0,
                            self.half_gap])
        self._dl = np.zeros(n_dl)                              # the current loop's delay line
        self._nz = np.zeros(NOISE_BLOCK)
        self._s[PS_NZI] = NOISE_BLOCK                          # drawn at the first step
        _plant_measured(self._s, self._p)                      # compile (or load the cache) now
        s0 = self._s.copy()
        s0[PS_NZI] = 0.0                                       # (a copy's first draw inside its block)
        if not self._hooks:
            _plant_step(0.0, s0, self._p, self._dl.copy(), np.zeros(NOISE_BLOCK))
        if self._terms is not None:
            _hooked_step(0.0, s0, self._p, self._dl.copy(), np.zeros(NOISE_BLOCK), *self._terms)

    def _motor_force(self, u: float) -> float:
        """F_m(u) = A1 u + A2 u|u| + A3 u³ [N] (eq. 3) under u [V], as :func:`_motor_force`."""
        return self.a1 * u + self.a2 * u * abs(u) + self.a3 * u * u * u

    def _acc(self, x: float, v: float, t: float, u: float) -> float:
        """ẍ [m/s²] at position x [m], velocity v [m/s], plant time t [s] under input u [V]:
        eq. (1) with the force curve of eq. (3), smooth Coulomb friction and the effects'
        hooks (thrust factor, forces, mass) in registry order."""
        f, m = self._hooked_force(self._motor_force(u), x, v, t)
        return f / m

    def _hooked_force(self, fm: float, x: float, v: float, t: float) -> tuple[float, float]:
        """(the force F [N], the moving mass m [kg]) of eq. (1) under the motor force fm [N] at
        x [m], ẋ = v [m/s], plant time t [s]: the thrust hooks on fm, smooth Coulomb friction,
        the force hooks and the mass hooks, in registry order."""
        for thrust in self._thrust:
            fm = thrust(fm, x, t)
        sf = _TWO_OVER_PI * math.atan(S_F_GAIN * v)
        f = fm - self.b * v - self.fc * sf + self.f0 + self.f_noise + self.f_ext
        for force in self._forces:
            f = force(f, x, v, t, sf)
        m = self.m
        for mass in self._masses:
            m = mass(m, t)
        return f, m

    def mass_at(self, t: float) -> float:
        """Moving mass [kg] at plant time t (payload change included)."""
        m = self.m
        for mass in self._masses:
            m = mass(m, t)
        return m

    def refill_noise(self) -> None:
        """The next block of normal draws from the plant's Generator, when the last is used up."""
        if self._s[PS_NZI] >= NOISE_BLOCK:
            self.rng.standard_normal(out=self._nz)
            self._s[PS_NZI] = 0.0

    def rehome(self, s: np.ndarray, p: np.ndarray, dl: np.ndarray, nz: np.ndarray) -> None:
        """Move the plant's state, parameters, delay line and noise block into rows the
        simulated driver keeps for all its plants (their values copied; the attributes read
        and write the rows from then on)."""
        s[:] = self._s
        p[:] = self._p
        dl[:] = self._dl
        nz[:] = self._nz
        self._s, self._p, self._dl, self._nz = s, p, dl, nz

    def step(self, u: float) -> None:
        """Hold u [V] (after the input delay) over one period; RK4 with ``substeps`` steps."""
        if self._compiled:
            self.refill_noise()
            _plant_step(u, self._s, self._p, self._dl, self._nz)
            return
        for delay in self._inputs:
            u = delay(u)
        if self._terms is not None:
            self.refill_noise()
            _hooked_step(u, self._s, self._p, self._dl, self._nz, *self._terms)
            return
        if self._inputs and not self._hooks:   # an input transform only: the plant without hooks
            self.refill_noise()
            _plant_step(u, self._s, self._p, self._dl, self._nz)
            return
        if self.noise > 0.0:
            self.f_noise = self.noise * float(self.rng.standard_normal())
        if self.stiction > 0.0 and self._stuck(u):
            x, xl = self.x, self.xl
            self._integrate(u)                 # time, delays and the current loop go on
            self.x, self.xd, self.xl, self.vl = x, 0.0, xl, 0.0
        else:
            self._integrate(u)
        if self.enc_sigma > 0.0:
            self.enc_noise = self.enc_sigma * float(self.rng.standard_normal())

    def _stuck(self, u: float) -> bool:
        """Karnopp stiction: the carriage is at rest (|ẋ| below the band) and the force applied
        to it at rest (motor, offset, noise, external push) is within the breakaway force."""
        if abs(self.xd) >= self.stick_v:
            return False
        if self._hooks and self.stiction_fx:
            return self._held_hooked(u)
        f = self._motor_force(u) + self.f0 + self.f_noise + self.f_ext
        return abs(f) <= self.stiction

    def _held_hooked(self, u: float) -> bool:
        """Karnopp stiction with the effects' hooks, for a carriage at rest: the force applied
        at rest includes the thrust terms and the effects' forces at rest (S_f = 0), and the
        breakaway the friction the effects add at rest in the direction of that force
        (S_f = ±1), as :func:`_held_hooked` (the same operations)."""
        x, t = self.x, self.t
        fm = self._motor_force(u)
        for thrust in self._thrust:
            fm = thrust(fm, x, t)
        f = fm + self.f0 + self.f_noise + self.f_ext
        for force in self._forces:
            f = force(f, x, 0.0, t, 0.0)
        d = 1.0 if f >= 0.0 else -1.0
        v = d * V_AT_REST
        g1 = g0 = 0.0
        for force in self._forces:
            g1 = force(g1, x, v, t, d)
            g0 = force(g0, x, v, t, 0.0)
        return abs(f) <= self.stiction - d * (g1 - g0)

    def _integrate(self, u: float) -> None:
        h = self.h
        if self._plain:
            self.x, self.xd, self.t = _rk4_plain(self.x, self.xd, self.t, u, h, self.substeps,
                                                 self.m, self.a1, self.a2, self.a3, self.b,
                                                 self.fc, self.f0, self.f_noise, self.f_ext)
        elif self._flex:
            self._step_flex(u)
        else:
            self._step_rigid(u)

    def _step_flex(self, u: float) -> None:
        """One period of the plant with the structural mode and/or the current loop."""
        f_cur = self._motor_force(u)
        if self._fdelay is not None:
            f_cur = self._fdelay(f_cur)
        f_prev, self.f_prev = self.f_prev, f_cur
        if not self._hooks:
            (self.x, self.xd, self.xl, self.vl, self.t, self.F) = _rk4_flex(
                self.x, self.xd, self.xl, self.vl, self.t, self.F, f_prev, f_cur, self.delta,
                self.tau_i, self.h, self.substeps, self.mc, self.ml, self.ks, self.cs, self.b,
                self.fc, self.f0, self.f_noise, self.f_ext, self.half_gap)
            return
        # general path: the same equations with the effects' hooks (python)
        h, F0, d, ti = self.h, self.F, self.delta, self.tau_i
        ml0, m_tot = self.ml, self.m

        def acc(xc, vc, xl, vl, t, tau, _args):
            f, m = self._hooked_force(_force_at(tau, F0, f_prev, f_cur, d, ti), xc, vc, t)
            if ml0 > 0.0:   # a mass change is the load's
                fsp = _coupling(xc - xl, vc - vl, self.ks, self.cs, self.half_gap)
                ac = (f - fsp) / self.mc
                return ac, fsp / (ml0 + m - m_tot)
            ac = f / m
            return ac, ac

        self.x, self.xd, self.xl, self.vl, self.t, tau = _rk4_with(acc)((), self.x, self.xd, self.xl, self.vl,
                                                                  self.t, h, self.substeps)
        self.F = _force_at(tau, F0, f_prev, f_cur, d, ti)

    def _step_rigid(self, u: float) -> None:
        """One period of the rigid plant with the effects' hooks (python)."""
        acc = self._acc

        def acc2(x, v, xl, vl, t, tau, _args):
            a = acc(x, v, t, u)
            return a, a

        self.x, self.xd, _, _, self.t, _ = _rk4_with(acc2)((), self.x, self.xd, 0.0, 0.0, self.t, self.h,
                                                   self.substeps)

    def measured(self) -> float:
        """Encoder reading [m]: x quantised to the resolution q (docs/control-law.md, Measurement)."""
        return _plant_measured(self._s, self._p)


class SimDriver(Driver):
    """The simulated gantry (default driver; used by CI). See the module docstring."""

    Options = SimOptions
    AxisOptions = SimAxisOptions

    def __init__(self, options: SimOptions, axis_options: dict, period_s: float):
        super().__init__(options, axis_options, period_s)
        rng = np.random.default_rng(options.seed)
        seeds = rng.integers(0, 2**63 - 1, size=len(self.axis_names))
        self.plants = [AxisPlant(axis_options[name], period_s, np.random.default_rng(int(s)),
                                 options.substeps)
                       for name, s in zip(self.axis_names, seeds)]
        n = len(self.plants)
        self.amp_enabled = np.zeros(n, dtype=bool)
        self._inject = np.zeros((n, 4), dtype=np.int64)   # cycles left: INJ_READ, INJ_NAN, INJ_AMP, INJ_PUSH
        self._jump_m = np.zeros(n)
        self._push_N = np.zeros(n)
        # every plant's whole period compiled (no effect hook, or only compiled effect terms; no
        # input transform): read and write are one compiled call for all axes, on rows kept
        # here (the plants' attributes read and write the same rows)
        self._compiled = all(p.period_compiled for p in self.plants)
        terms = [p._terms if p._terms is not None and p.period_compiled else None for p in self.plants]
        m = max([len(t[0]) for t in terms if t is not None] + [1])
        w = max([t[1].shape[1] for t in terms if t is not None] + [1])
        self._NT = np.zeros(n, dtype=np.int64)
        self._TC = np.zeros((n, m), dtype=np.int64)
        self._TT = np.zeros((n, m, w))
        self._TL = np.zeros((n, m), dtype=np.int64)
        for i, t in enumerate(terms):
            if t is not None:
                k = len(t[0])
                self._NT[i] = k
                self._TC[i, :k], self._TT[i, :k, :t[1].shape[1]], self._TL[i, :k] = t
        self._S, self._P = np.zeros((n, N_PS)), np.zeros((n, N_PP))
        self._DL = np.zeros((n, max([p._dl.size for p in self.plants] + [1])))
        self._NZ = np.zeros((n, NOISE_BLOCK))
        for i, p in enumerate(self.plants):
            p.rehome(self._S[i], self._P[i], self._DL[i, :p._dl.size], self._NZ[i])
            if p.period_compiled:       # (any other plant draws its first block at its first step,
                p.refill_noise()        # one with Python hooks one draw at a time)
        self.applied_u = np.zeros(n)   # voltage at the amplifier output [V]
        #: each carriage's true position at the last read [m] (n,): the plant's x, which the
        #: encoder reads with its steps, noise and interpolation error (and an injected jump),
        #: in machine coordinates (homing's offset added): a simulated ballbar or interferometer
        #: (ISO 230-4's instrument apart from the machine's feedback). Real drives have no such
        #: attribute; :mod:`motorctl.app.circle_test` evaluates it beside the encoders
        self.true_position_m = np.zeros(n)
        self._u_cmd, self._en_cmd = np.zeros(n), np.zeros(n, dtype=bool)   # commands of other arrays
        self._io = self._sim_io()
        # the compiled read and write, compiled (or loaded from the cache) now and run on copies
        self._read = entry(_sim_read, self._io, False)
        self._read(self._sim_io(copies=True), False)
        self._write = None
        self._u_ok = self._en_ok = None       # the last output arrays seen to have the right types,
        self._io_ok = self._io                # and the bundle that commands from them
        self._refill = False                  # a plant's block of noise draws is used up
        self._refresh = None                  # the rehearsal's refresh of its copies (compiled write only)
        if self._compiled:
            self._write = entry(_sim_write, self._io, False)
            self._write(self._sim_io(copies=True), False)
            self._scratch = self._sim_arrays(copies=True)     # the rehearsal's copies
            self._scratch_io = bundle(_make_sim_io, SIM_FIELDS, self._scratch)
            self._refresh = entry(_sim_refresh, self._io, self._scratch_io)
        self.watchdog_ns = int(options.watchdog_s * 1e9)
        self.watchdog_bites = 0
        self._last_write_ns = 0
        self._bite_pending = False
        self._period_ns = int(round(period_s * 1e9))
        for i, p in enumerate(self.plants):
            self.position_m[i] = p.measured()
            self.true_position_m[i] = p.x
        # homing inputs: the switch, the index latch (NaN until it latched once armed), the
        # offset homing set (added to the encoder's reading)
        self._switch_m = [axis_options[a].home_switch_m for a in self.axis_names]
        self._index_m = [axis_options[a].index_pulse_m for a in self.axis_names]
        self._homing_io = [j for j in range(n) if self._switch_m[j] is not None or self._index_m[j] is not None]
        self.home_switch = np.zeros(n, dtype=bool)
        self.index_latch_m = np.full(n, np.nan)
        self._armed = np.zeros(n, dtype=bool)
        self._raw_last = np.full(n, np.nan)
        self.position_offset_m = np.zeros(n)
        self._offset_on = False

    # ------------------------------------------------------------------ homing inputs
    @property
    def has_homing_inputs(self) -> bool:
        return bool(self._homing_io)

    def arm_index(self, i: int) -> None:
        """Latch the position at axis i's next index pulse (``index_latch_m[i]``, NaN until)."""
        self.index_latch_m[i] = np.nan
        self._armed[i] = True

    def set_position_offset(self, i: int, delta_m: float) -> None:
        """Shift axis i's reported position by ``delta_m`` [m] from the next read (homing)."""
        self.position_offset_m[i] += delta_m
        self._offset_on = bool(np.any(self.position_offset_m != 0.0))

    def _homing_inputs(self) -> None:
        """Between cycles: the switch and the index pulse from the encoder's raw reading; the
        index latches the reading (offset included) of the cycle the mark was crossed in."""
        for i in self._homing_io:
            raw = self.position_m[i] - self.position_offset_m[i]
            sw = self._switch_m[i]
            self.home_switch[i] = sw is not None and raw <= sw
            mark = self._index_m[i]
            last = self._raw_last[i]
            if self._armed[i] and mark is not None and last == last and (last - mark) * (raw - mark) <= 0.0 \
                    and last != raw:
                self.index_latch_m[i] = mark + self.position_offset_m[i]
                self._armed[i] = False
            self._raw_last[i] = raw

    def _sim_arrays(self, copies: bool = False, command: tuple | None = None) -> tuple:
        """The exchange's arrays in the order of :data:`SIM_FIELDS`, or copies of them (for a
        call that changes nothing); ``command``: the (u [V], enable) arrays the write is to
        read its command from (default: the driver's own)."""
        arrays = (self.position_m, self.read_error, self.amp_fault, self.amp_enabled, self.applied_u, self._S,
                  self._P, self._DL, self._NZ, self._inject, self._jump_m, self._push_N, self._TC, self._TT,
                  self._TL, self._NT) + (command or (self._u_cmd, self._en_cmd)) + (self.true_position_m,)
        return tuple(a.copy() for a in arrays) if copies else arrays

    def _sim_io(self, copies: bool = False, command: tuple | None = None) -> SimIO:
        """:meth:`_sim_arrays` as the bundle the compiled read and write take (:class:`SimIO`)."""
        return bundle(_make_sim_io, SIM_FIELDS, self._sim_arrays(copies, command))

    def _watchdog(self, now: int) -> bool:
        """The drive's command watchdog, checked at every exchange (read and write) at ``now``
        (CLOCK_MONOTONIC [ns]): a stall anywhere in the host's cycle (between read and write
        included) counts from the last command received. Returns True when it bites; the fault
        is then reported by the next read (it stays pending until one has seen it)."""
        gap = now - self._last_write_ns
        if gap <= self.watchdog_ns:
            return False
        self.watchdog_bites += 1
        self.amp_enabled[:] = False
        self.applied_u[:] = 0.0
        n = min(gap // self._period_ns, self.options.watchdog_max_catchup)
        for plant in self.plants:
            for _ in range(n):
                plant.step(0.0)
        self._bite_pending = True
        self._last_write_ns = now
        return True

    def _service(self) -> None:
        if self._homing_io:
            self._homing_inputs()
        # the next blocks of noise draws, between cycles (a refill from numpy's Generator
        # took 60-70 us, once every 128 cycles, inside the write)
        if self._refill:
            self._refill_noise()

    def _refill_noise(self) -> None:
        for plant in self.plants:
            plant.refill_noise()
        self._refill = False

    def _rehearse(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        # the whole exchange compiled: the copies refreshed, then the driver's own compiled read
        # and write on them (the entries the real exchange calls); otherwise nothing
        if self._refresh is not None and u_V is self._u_ok and enable is self._en_ok:
            self._refresh(self._io_ok, self._scratch_io)
            self._read(self._scratch_io, False)
            self._write(self._scratch_io, False)

    def read(self) -> None:
        if self.watchdog_ns and self._last_write_ns:
            self._watchdog(time.monotonic_ns())
        bitten = self._bite_pending
        self._bite_pending = False
        self._read(self._io_ok, bitten)      # the bundle the write and the rehearsal use (the same arrays)
        if self._offset_on:                  # homed: the reading in machine coordinates
            self.position_m += self.position_offset_m
            self.true_position_m += self.position_offset_m

    def write(self, u_V: np.ndarray, enable: np.ndarray) -> None:
        # a command that arrives after the watchdog expired finds the amplifier already off.
        # The command's arrival is timed here, as it enters: timed after the write, a stall of
        # the host between the two (a preempted or stopped loop process) would be taken for
        # the command's own lateness and never counted
        now = time.monotonic_ns() if self.watchdog_ns else 0
        bitten = bool(self.watchdog_ns and self._last_write_ns and self._watchdog(now))
        if self._compiled:
            if u_V is not self._u_ok or enable is not self._en_ok:
                u_V, enable = self._checked(u_V, enable)
            if u_V is self._u_ok and enable is self._en_ok:
                io = self._io_ok              # the checked arrays themselves: nothing to pass
            else:
                self._u_cmd[:] = u_V
                self._en_cmd[:] = enable
                io = self._io
            if self._refill:                  # service() was not called since the last write
                self._refill_noise()
            if self._write(io, bitten):       # refilled by service(), between cycles
                self._refill = True
            if self.watchdog_ns:
                self._last_write_ns = now
            return
        for i, plant in enumerate(self.plants):
            on = bool(enable[i]) and not self.amp_fault[i] and not bitten
            self.amp_enabled[i] = on
            u = float(u_V[i]) if on else 0.0
            if u != u:  # NaN never reaches the amplifier
                u = 0.0
            self.applied_u[i] = u
            inj = self._inject[i]
            if inj[3] > 0:
                inj[3] -= 1
                plant.f_ext = self._push_N[i]
            else:
                plant.f_ext = 0.0
            plant.step(u)
        if self.watchdog_ns:
            self._last_write_ns = now

    def _checked(self, u_V, enable):
        """u_V and enable as the compiled write takes them (float64 and bool, (n,), contiguous):
        as given when they are (then remembered with a bundle that reads them, so the loop's own
        arrays are checked once and never passed again), else converted."""
        n = len(self.plants)
        ok = (isinstance(u_V, np.ndarray) and u_V.dtype == np.float64 and u_V.shape == (n,)
              and u_V.flags.c_contiguous and isinstance(enable, np.ndarray) and enable.dtype == np.bool_
              and enable.shape == (n,) and enable.flags.c_contiguous)
        if ok:
            self._u_ok, self._en_ok = u_V, enable
            self._io_ok = self._sim_io(command=(u_V, enable))
            return u_V, enable
        return (np.ascontiguousarray(np.broadcast_to(np.asarray(u_V, dtype=np.float64), (n,))),
                np.ascontiguousarray(np.broadcast_to(np.asarray(enable, dtype=np.bool_), (n,))))

    def _stop(self, timeout_s: float) -> list[StopCheck]:
        """0 V with every amplifier off (one more period of plant time), read back from the
        simulated amplifier's output."""
        n = len(self.plants)
        self.write(np.zeros(n), np.zeros(n, dtype=bool))
        return [StopCheck(a, not self.amp_enabled[i] and self.applied_u[i] == 0.0,
                          f"amplifier output {self.applied_u[i]:.3f} V, amplifier "
                          f"{'on' if self.amp_enabled[i] else 'off'} (simulated)")
                for i, a in enumerate(self.axis_names)]

    def _close(self) -> None:
        self.amp_enabled[:] = False
        self.applied_u[:] = 0.0

    FAULT_KINDS = ("read_error", "nan", "amp_fault", "encoder_jump", "push")

    def inject(self, kind: str, axis: str, cycles: int = 1, jump_m: float = 0.0,
               force_N: float = 0.0) -> None:
        """Inject a fault on ``axis`` for ``cycles`` reads (tests only, not inside the cycle).

        kind: 'read_error' (exchange fails), 'nan' (position NaN), 'amp_fault' (amplifier
        reports a fault), 'encoder_jump' (a permanent offset of ``jump_m`` [m]), 'push' (an
        external force ``force_N`` [N] on the carriage for ``cycles`` periods).
        Raises:
            ValueError: unknown kind or axis.
        """
        if axis not in self.axis_names:
            raise ValueError(f"unknown axis {axis!r}; axes: {', '.join(self.axis_names)}")
        i = self.axis_names.index(axis)
        slots = {"read_error": 0, "nan": 1, "amp_fault": 2, "push": 3}
        if kind == "encoder_jump":
            self._jump_m[i] += jump_m
        elif kind in slots:
            if kind == "push":
                self._push_N[i] = float(force_N)
            self._inject[i][slots[kind]] = int(cycles)
        else:
            raise ValueError(f"unknown fault kind {kind!r}; allowed: {', '.join(self.FAULT_KINDS)}")

    def describe(self) -> dict:
        """Simulated truth per axis for the log header: θ (6), A1, and the effects switched on."""
        out = {}
        for name, p in zip(self.axis_names, self.plants):
            opt = p.opt
            out[name] = {
                "theta_true": opt.physical().theta().tolist(),
                "a1_N_per_V": opt.a1_N_per_V,
                "effects": opt.effects.model_dump(exclude_none=True),
                "input_delay_s": opt.input_delay_s,
                "force_noise_N": opt.force_noise_N,
            }
            extra = {k: getattr(opt, k) for k in _UNMODELLED if getattr(opt, k)}
            if extra:
                out[name]["unmodelled"] = extra
        return {"simulated": out}
