"""Strict YAML configuration: one clear error naming the file and the key, nothing started.

Checks, in order:
  1. YAML syntax and **duplicate keys** (PyYAML silently keeps the last one; we refuse).
  2. The schema (pydantic, strict): unknown keys, wrong types, out-of-range values.
  3. The driver's own option schemas (found through the ``motorctl.drivers`` entry points).
  4. Cross-field rules: θ_min ≤ θ̂(0) ≤ θ_max, θ_min < θ_max, λ_max(Γ(0)) ≤ ρ_M, the paper's
     Assumption 2 (f_u monotonic on |u| ≤ u_lim over the θ5/θ6 box), trajectory moves fit
     their period, soft limits contain the program.

The layout (see ``configs/gantry.yaml``)::

    loop:    {rate_hz, clock, realtime: {...}, overrun_policy, overrun_hold_cycles, overrun_ramp_s}
    daemon:  {socket, group, log_dir, flush_s, event_before_s, event_after_s, stop_settle_s, ...}
    driver:  {type: sim, <driver options>}
    axes:
      X:
        driver:     {<per-axis driver options>}
        controller: {type: c1|c2|pid|<a registered law>, u_lim, theta_min, theta_max, theta_hat0,
                     compensation: {...},                     (shared by every law)
                     mode, k_s, k1, gamma_d, d_hat_max, gamma0, filter: {omega_f}, mu, nu,
                     rho_M, theory: {...},                     (C1 and C2's shared keys)
                     c1: {...}, c2: {...}, pid: {...}}         (one law's own settings)
        trajectory: {points, move_times_s, period_s, v_max, a_max, j_max}
        limits:     {soft_min_m, soft_max_m, following_error_m, min_following_error_m, ...}
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal, get_args, get_origin

import yaml
from pydantic import BaseModel, Field, StringConstraints, ValidationError, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError

from motorctl.control import CONTROLLER_NAMES, configured_controllers, controller_class
from motorctl.control.params import ControllerConfig
from motorctl.driver import Driver, load_driver_class
from motorctl.inputs import MAX_CONFIG_BYTES, ConfigError, InputError, read_text, summarize
from motorctl.loop.rt import RealtimeConfig
from motorctl.loop.safety import LimitsConfig
from motorctl.loop.timebase import Timebase
from motorctl.loop.trajectory import TrajectoryConfig
from motorctl.motion.gcode import GcodeSettings
from motorctl.recorder.flight import stall_bound_s
from motorctl.schema import StrictModel, quantity


# --------------------------------------------------------------------------- YAML
class _StrictLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """SafeLoader that refuses duplicate mapping keys and reads YAML 1.2 floats: ``5e3`` and
    ``1e-6`` are numbers (YAML 1.1, PyYAML's default, reads them as strings). libyaml's parser
    where PyYAML has it (its wheels do): the same documents, about ten times faster than the
    pure-Python one (configs/gantry.yaml: 3 ms instead of 37 ms), which every command and
    config check pays; the syntax errors' wording is libyaml's then."""


_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def _construct_mapping(loader, node, deep=False):
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r} (first at line {seen[key] + 1})", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_yaml(path: str | Path) -> dict:
    """Parse a YAML config file strictly (a regular UTF-8 file of at most
    :data:`motorctl.inputs.MAX_CONFIG_BYTES`).

    Raises:
        ConfigError: missing, not a regular file, too large, not UTF-8, a syntax error, a
        duplicate key, or a top level that is not a mapping.
    """
    path = Path(path)
    try:
        text = read_text(path, "config", MAX_CONFIG_BYTES)
    except InputError as exc:
        msg = str(exc)
        raise ConfigError(path, "", msg[len(str(path)) + 2:] if msg.startswith(f"{path}: ") else msg) from None
    try:
        data = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 (SafeLoader subclass)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(path, where, exc.problem or str(exc)) from None
    except yaml.YAMLError as exc:
        raise ConfigError(path, "", f"not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise ConfigError(path, "", "the top level must be a mapping with 'loop', 'driver' and 'axes'")
    return data


# --------------------------------------------------------------------------- schema
class LoopConfig(StrictModel):
    """Loop rate, clock, run length, real-time set-up and the overrun policy.

    overrun_policy: 'count' (count and skip missed periods, ros2_control's rule) or 'ramp'
    (on a missed period every driven axis holds its last output for overrun_hold_cycles,
    ramps it to 0 V over overrun_ramp_s, then the amplifier is disabled and FAULT_OVERRUN
    latches).
    """

    rate_hz: Annotated[float, Field(gt=0, le=20000)] = 5000.0
    clock: Literal["wall", "virtual"] = "wall"
    duration_s: quantity(1e-4, 1e7, "s") = 40.0
    realtime: RealtimeConfig = RealtimeConfig()
    overrun_policy: Literal["count", "ramp"] = "count"
    overrun_hold_cycles: Annotated[int, Field(ge=0, le=1000)] = 5
    overrun_ramp_s: Annotated[float, Field(ge=0, le=1.0)] = 0.01


def parse_listen(text: str) -> tuple[str, int]:
    """"host:port" → (host, port). Raises ValueError naming what is allowed."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{text!r} is not host:port; allowed: e.g. 127.0.0.1:8080 (port 1-65535)")
    return host.strip("[]"), int(port)


class ScopeConfig(StrictModel):
    """The live scope page (docs/daemon.md): listen = "host:port" of its web server, loopback
    unless the config names another address."""

    listen: str = "127.0.0.1:8080"

    @field_validator("listen")
    @classmethod
    def _host_port(cls, v: str) -> str:
        parse_listen(v)
        return v


class FoxgloveConfig(ScopeConfig):
    """The scope's channels over Foxglove's WebSocket protocol: listen = "host:port"."""

    listen: str = "127.0.0.1:8765"


class MetricsConfig(ScopeConfig):
    """Prometheus metrics (docs/metrics.md): listen = "host:port" of the ``/metrics`` endpoint
    (9464: the port OpenTelemetry's Prometheus exporter registered)."""

    listen: str = "127.0.0.1:9464"


class OpcuaConfig(StrictModel):
    """The OPC UA server (docs/opcua.md, the ``opcua`` extra): endpoint = its opc.tcp URL;
    anonymous: what a session without a user may do ('read': browse, read, subscribe; 'off':
    nothing); security: the policies offered ('None', 'Basic256Sha256' with Sign or
    SignAndEncrypt); certificate / private_key: the server's X.509 PEM files (None: a
    self-signed pair made in the daemon's log_dir at first start); pki_dir: the client
    certificates' trust list, PKI_DIR/trusted (accepted) and PKI_DIR/rejected (refused ones kept
    for the operator to accept, ``motorctl opcua trust``) (None: LOG_DIR/opcua)."""

    endpoint: str = "opc.tcp://127.0.0.1:4840/motorctl"
    anonymous: Literal["read", "off"] = "read"
    security: list[Literal["None", "Basic256Sha256"]] = ["None", "Basic256Sha256"]
    certificate: str | None = None
    private_key: str | None = None
    pki_dir: str | None = None

    @field_validator("endpoint")
    @classmethod
    def _opc_tcp(cls, v: str) -> str:
        if not v.startswith("opc.tcp://"):
            raise ValueError(f"{v!r} is not an opc.tcp:// URL; allowed: e.g. opc.tcp://127.0.0.1:4840/motorctl")
        return v


class DaemonConfig(StrictModel):
    """The service (``motorctl daemon``): control socket, run logs, flight recorder, stop ramp.

    socket: Unix-domain control socket path (mode 0660); group: its group (name or gid;
    None = the daemon's own group); log_dir: where run logs go; flush_s: longest time between
    two fdatasync of the run log [s] (the loop latches every axis when the recorder stalls
    for 2·flush_s + 1 s); event_before_s / event_after_s: the window kept around
    each fault in an event log [s]; overrun_event_before_s / overrun_event_after_s: the
    (shorter) window kept around an overrun [s]; max_event_logs: per run; stop_settle_s: how
    long an axis holds its final position before 0 V and amplifier off [s];
    allow_fault_injection: accept ``motorctl inject`` (simulated driver only).
    scope: the live scope page served by the I/O process (:class:`ScopeConfig`; None: off).
    foxglove: the same channels to Foxglove (:class:`FoxgloveConfig`; None: off).
    metrics: Prometheus ``/metrics`` from a process of its own (:class:`MetricsConfig`, the
    ``metrics`` extra, docs/metrics.md; None: off).
    opcua: the OPC UA server (:class:`OpcuaConfig`, the ``opcua`` extra; None: off).
    users_file: the operators' accounts (YAML of hashed passwords and roles,
    :mod:`motorctl.app.users`) that the OPC UA server and the operator page check; None: no
    logins (read-only views). login_lockout_s: how long a user name stays locked after its 6th
    failed login within a minute (both surfaces, :mod:`motorctl.app.login`; ``motorctl users
    unlock`` clears it) [s].
    motion_lead_s: commanded motion's setpoints kept ahead of the loop [s] (the setpoint ring
    holds twice as much, at least 1 s): the longest the I/O process may be starved of the CPU
    before the loop runs dry and brakes to rest (an underrun, docs/motion.md); below the
    recorder's stall bound 2·flush_s + 1 s; a hold, an abort or an override rewrites the rows
    beyond a 4 ms guard whatever the lead (wider when the rewrite's 0.25 s take longer to generate).
    The default 1 s: 0.5 s was not enough on the 2-core VM beside CPU hogs, where the filler,
    real-time or not, was held off 0.2-1.0 s at times, several daemons' at the same moment (the
    VM's CPU steal, by every sign; docs/benchmarks.md). max_program_bytes: the largest G-code program the daemon takes
    (sent in chunks; a larger one is refused by name before anything is planned) [bytes].

    Retention of ``log_dir`` (docs/daemon.md): log_segment_bytes: largest run-log segment
    [bytes]; log_segment_s: a segment is closed at this age at the latest [s];
    log_budget_bytes: most bytes of run logs and event logs kept in log_dir (at least two
    segments) [bytes]; log_max_age_s: routine segments older than this are deleted [s]
    (event logs go only when the budget needs it, after the routine segments, or when they
    hold more than the budget less two segments).
    """

    socket: str = "/run/motorctl/motorctl.sock"
    group: str | int | None = None
    log_dir: str = "/var/log/motorctl"
    flush_s: Annotated[float, Field(gt=0, le=1.0)] = 0.5
    event_before_s: Annotated[float, Field(ge=0, le=10.0)] = 2.0
    event_after_s: Annotated[float, Field(ge=0, le=10.0)] = 1.0
    overrun_event_before_s: Annotated[float, Field(ge=0, le=10.0)] = 0.1
    overrun_event_after_s: Annotated[float, Field(ge=0, le=10.0)] = 0.1
    max_event_logs: Annotated[int, Field(ge=0)] = 20
    stop_settle_s: Annotated[float, Field(ge=0, le=5.0)] = 0.1
    allow_fault_injection: bool = False
    scope: ScopeConfig | None = None
    foxglove: FoxgloveConfig | None = None
    metrics: MetricsConfig | None = None
    opcua: OpcuaConfig | None = None
    users_file: str | None = None
    login_lockout_s: Annotated[float, Field(ge=1.0, le=7 * 86400.0)] = 900.0
    motion_lead_s: Annotated[float, Field(ge=0.05, le=3.0)] = 1.0
    max_program_bytes: Annotated[int, Field(ge=1 << 16, le=1 << 40)] = 1 << 30
    log_segment_bytes: Annotated[int, Field(ge=1 << 20, le=1 << 40)] = 512 << 20
    log_segment_s: Annotated[float, Field(ge=1.0, le=7 * 86400.0)] = 3600.0
    log_budget_bytes: Annotated[int, Field(ge=2 << 20, le=1 << 50)] = 16 << 30
    log_max_age_s: Annotated[float, Field(ge=60.0, le=3650 * 86400.0)] = 30 * 86400.0

    @field_validator("motion_lead_s")
    @classmethod
    def _lead_below_the_stall_bound(cls, v: float, info: ValidationInfo) -> float:
        flush = info.data.get("flush_s")
        bound = None if flush is None else stall_bound_s(flush)
        if bound is not None and v >= bound:
            raise PydanticCustomError(
                "lead_too_long", "not below the recorder's stall bound 2 x flush_s + 1 s = {bound} s (an I/O "
                "process starved that long latches 'recorder stalled' before the lead runs out); allowed: "
                "below it", {"bound": bound})
        return v

    @field_validator("log_budget_bytes")
    @classmethod
    def _budget_holds_two_segments(cls, v: int, info: ValidationInfo) -> int:
        seg = info.data.get("log_segment_bytes")
        if seg is not None and v < 2 * seg:
            raise PydanticCustomError(
                "budget_too_small", "less than two segments; allowed: at least "
                "2 x log_segment_bytes = {need}", {"need": 2 * seg})
        return v


class HomingConfig(StrictModel):
    """Per-axis homing (YAML ``axes.NAME.homing``), LinuxCNC's sequence: search the home switch
    in ``direction`` at ``search_speed``, back off it at ``latch_speed`` until the encoder's
    index pulse latches (at most ``back_off_m``), and give the latched position the coordinate
    ``position_m``. ``required``: command-mode motion is refused until the axis is homed."""

    direction: Literal[-1, 1] = -1
    search_speed_m_per_s: quantity(1e-5, 1.0, "m/s") = 0.02
    latch_speed_m_per_s: quantity(1e-6, 0.1, "m/s") = 0.005
    search_distance_m: quantity(1e-4, 10.0, "m") = 0.5
    back_off_m: quantity(1e-5, 1.0, "m") = 0.01
    position_m: quantity(-100.0, 100.0, "m") = 0.0
    required: bool = False


class AxisConfig(StrictModel):
    driver: dict = {}
    controller: ControllerConfig
    trajectory: TrajectoryConfig = TrajectoryConfig()
    limits: LimitsConfig = LimitsConfig()
    homing: HomingConfig | None = None


class DriverSection(StrictModel):
    type: str = "sim"
    model_config = StrictModel.model_config | {"extra": "allow"}


#: an axis name: a letter, then letters, digits or '_' (it is a column prefix and a CLI word)
AxisName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z][A-Za-z0-9_]{0,31}$")]


class GantryConfig(StrictModel):
    #: the machine's name in its run logs' headers (a fleet's logs are grouped by it); None: the
    #: host name
    machine_id: Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")] | None = None
    loop: LoopConfig = LoopConfig()
    daemon: DaemonConfig = DaemonConfig()
    driver: DriverSection = DriverSection()
    axes: Annotated[dict[AxisName, AxisConfig], Field(min_length=1)]
    #: the G-code reader's machine words, G28 reference point, optional stop (GcodeSettings)
    gcode: GcodeSettings = Field(default_factory=GcodeSettings)


class LoadedConfig:
    """A validated config: ``raw`` (schema model), the driver class and its parsed options."""

    def __init__(self, path: Path, cfg: GantryConfig, driver_cls: type[Driver],
                 driver_options, axis_driver_options: dict):
        self.path = path
        self.cfg = cfg
        self.driver_cls = driver_cls
        self.driver_options = driver_options
        self.axis_driver_options = axis_driver_options

    @property
    def axes(self) -> dict[str, AxisConfig]:
        return self.cfg.axes

    @property
    def period_s(self) -> float:
        return 1.0 / self.cfg.loop.rate_hz

    @property
    def timebase(self) -> Timebase:
        """The loop's :class:`Timebase` (the one seconds → cycles conversion)."""
        return Timebase(self.period_s)

    def make_driver(self, axis_names=None) -> Driver:
        names = list(axis_names) if axis_names else list(self.axes)
        return self.driver_cls(self.driver_options, {a: self.axis_driver_options[a] for a in names},
                               self.period_s)


def _fmt_loc(prefix: str, loc) -> str:
    parts = [prefix] if prefix else []
    for item in loc:
        if isinstance(item, int):
            parts[-1] = f"{parts[-1]}[{item}]" if parts else f"[{item}]"
        else:
            parts.append(str(item))
    return ".".join(parts)


def _validate(path: Path, model, data, prefix: str = ""):
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = tuple(x for x in err["loc"] if not (isinstance(x, str) and x.startswith("function-")))
        msg = err["msg"]
        if loc and loc[-1] == "[key]":         # a mapping key itself is wrong (an axis name)
            loc = loc[:-2]
            msg = f"{summarize(err['input'])} is not a valid name: {msg}"
        key = _fmt_loc(prefix, loc)
        if err["type"] == "string_pattern_mismatch" and "is not a valid name" in msg:
            msg = (f"{summarize(err['input'])} is not a valid name; allowed: a letter, then "
                   f"letters, digits or '_' (at most 32)")
        elif err["type"] == "extra_forbidden":
            allowed = ", ".join(model_fields_at(model, loc[:-1])) or "none"
            msg = f"unknown key; allowed here: {allowed}"
        elif err["type"] == "value_error" and ("physical range" in msg or "no physical value" in msg):
            msg = msg.removeprefix("Value error, ")      # it names the value, the range and the unit
        elif "input" in err and err["type"] != "missing" and "is not a valid name" not in msg:
            msg = f"{msg} (got {summarize(err['input'])})"
        more = f" (and {len(exc.errors()) - 1} more problem(s))" if len(exc.errors()) > 1 else ""
        raise ConfigError(path, key, msg + more) from None


def _submodel(ann):
    """(model class, keyed) found inside an annotation: M, M | None, Annotated[M, ...], dict[str, M]."""
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return ann, False
    keyed = get_origin(ann) is dict
    for arg in get_args(ann):
        found, _ = _submodel(arg)
        if found is not None:
            return found, keyed
    return None, False


def model_fields_at(model, loc) -> list[str]:
    """Field names of the sub-model reached by following ``loc`` (for 'allowed keys' hints)."""
    cur, skip = model, False
    for item in loc:
        if skip:  # a dict key such as an axis name
            skip = False
            continue
        field = cur.model_fields.get(item) if cur is not None else None
        if field is None:
            return []
        cur, skip = _submodel(field.annotation)
    return list(cur.model_fields) if cur is not None else []


def _check_laws(path: Path, c: ControllerConfig, pre: str) -> None:
    """Each key of a ``controller:`` section belongs to a registered law, each configured law's
    settings pass its own model, and the active ``type`` is configured."""
    unknown = c.unknown_keys()
    if unknown:
        raise ConfigError(path, f"{pre}.{unknown[0]}",
                          f"unknown key; allowed here: {', '.join(c.allowed_keys())}")
    for law in CONTROLLER_NAMES:
        if not c.configures(law):
            continue
        own, shared = c.law_data(law)
        try:
            c.settings(law)
        except ValidationError as exc:
            loc = exc.errors()[0]["loc"]
            mine = not isinstance(own, dict) and own is not None or (
                isinstance(own, dict) and bool(loc) and loc[0] in own)
            data = own if not isinstance(own, dict) and own is not None else {**shared, **(own or {})}
            _validate(path, controller_class(law).Settings, data, f"{pre}.{law}" if mine else pre)
            raise
    if c.type not in configured_controllers(c):
        known = c.type in CONTROLLER_NAMES
        raise ConfigError(path, f"{pre}.type",
                          f"{c.type!r} " + ("needs its settings in this section (e.g. 'pid:')"
                                            if known else "is not a controller")
                          + f"; allowed here: {', '.join(configured_controllers(c))}")


def _cross_checks(path: Path, cfg: GantryConfig) -> None:
    sections = {n: a.controller for n, a in cfg.axes.items()}
    for name, ax in cfg.axes.items():
        c = ax.controller
        pre = f"axes.{name}.controller"
        _check_laws(path, c, pre)
        for i in range(6):
            if not c.theta_min[i] < c.theta_max[i] and not (i >= 4 and c.theta_min[i] == c.theta_max[i] == 0):
                raise ConfigError(path, f"{pre}.theta_min[{i}]",
                                  f"must be below theta_max[{i}] ({c.theta_min[i]} >= {c.theta_max[i]})")
            if not c.theta_min[i] <= c.theta_hat0[i] <= c.theta_max[i]:
                raise ConfigError(path, f"{pre}.theta_hat0[{i}]",
                                  f"{c.theta_hat0[i]} is outside [theta_min, theta_max] = "
                                  f"[{c.theta_min[i]}, {c.theta_max[i]}]")
        if c.theta_min[0] <= 0:
            raise ConfigError(path, f"{pre}.theta_min[0]",
                              f"theta1 = M/A1 must be bounded away from 0 (got {c.theta_min[0]}); allowed: > 0")
        for law in configured_controllers(c):
            for key, why in controller_class(law).check(c.settings(law), c):
                raise ConfigError(path, f"{pre}.{key}", why)
        t = ax.trajectory
        tpre = f"axes.{name}.trajectory"
        if len(t.points) > 1 and len(t.move_times_s) != len(t.points):
            raise ConfigError(path, f"{tpre}.move_times_s",
                              f"needs one start time per point ({len(t.points)}), got {len(t.move_times_s)}")
        try:
            prog = t.program()
        except ValueError as exc:
            raise ConfigError(path, tpre, str(exc)) from None
        lim = ax.limits
        lpre = f"axes.{name}.limits"
        if not lim.soft_min_m < lim.soft_max_m:
            raise ConfigError(path, f"{lpre}.soft_min_m", "must be below soft_max_m")
        lo, hi = min(prog.points), max(prog.points)
        if lo < lim.soft_min_m or hi > lim.soft_max_m:
            raise ConfigError(path, f"{tpre}.points",
                              f"program spans [{lo}, {hi}] m, outside the soft limits "
                              f"[{lim.soft_min_m}, {lim.soft_max_m}] m")
        if lim.min_following_error_m > lim.following_error_m:
            raise ConfigError(path, f"{lpre}.min_following_error_m", "must not exceed following_error_m")
        if not lim.i2t_continuous_V < lim.i2t_peak_V:
            raise ConfigError(path, f"{lpre}.i2t_continuous_V",
                              f"{lim.i2t_continuous_V:g} V must be below i2t_peak_V ({lim.i2t_peak_V:g} V)")
    # checks across axes, once every axis's own sections are known good (a pair law's halves)
    for name, ax in cfg.axes.items():
        c = ax.controller
        for law in configured_controllers(c):
            for key, why in controller_class(law).check_axes(name, c.settings(law), sections, 1.0 / cfg.loop.rate_hz):
                raise ConfigError(path, f"axes.{name}.controller.{key}", why)


def load_config(path: str | Path, check_budget: bool = True) -> LoadedConfig:
    """Load and fully check a config. Raises :class:`ConfigError` (one clear line) on any problem."""
    path = Path(path)
    return config_from_dict(load_yaml(path), path, check_budget)


def config_from_dict(data: dict, source: str | Path = "<dict>", check_budget: bool = True) -> LoadedConfig:
    """Check a config given as a dict (the parsed YAML); ``source`` names it in errors."""
    path = Path(source)
    cfg = _validate(path, GantryConfig, data)
    dtype = cfg.driver.type
    try:
        driver_cls = load_driver_class(dtype)
    except KeyError as exc:
        raise ConfigError(path, "driver.type", str(exc.args[0])) from None
    dopts = {k: v for k, v in (cfg.driver.model_extra or {}).items()}
    driver_options = _validate(path, driver_cls.Options, dopts, "driver")
    axis_opts = {}
    for name, ax in cfg.axes.items():
        axis_opts[name] = _validate(path, driver_cls.AxisOptions, ax.driver, f"axes.{name}.driver")
    _cross_checks(path, cfg)
    loaded = LoadedConfig(path, cfg, driver_cls, driver_options, axis_opts)
    try:
        driver = loaded.make_driver()      # parse only: no I/O; checks what spans axes
    except ValueError as exc:              # e.g. two axes' fields on the same CAN bytes
        raise ConfigError(path, "driver", str(exc)) from None
    _check_command_limits(path, cfg, driver)
    _check_read_timeout(path, cfg, driver_options)
    if check_budget:
        rate = cfg.loop.rate_hz
        b = driver.budget(rate)
        if rate > b.max_rate_hz:
            hint = f"; {b.suggestion}" if b.suggestion else ""
            raise ConfigError(path, "loop.rate_hz",
                              f"{rate:g} Hz is more than the bus can carry: {b.detail} "
                              f"(bus time {b.cycle_time_s * 1e6:.1f} us per cycle, at most "
                              f"{b.max_rate_hz:.0f} Hz){hint}")
    return loaded


#: the most of the period a bus driver's read may wait for its answers on a wall clock
READ_TIMEOUT_MAX_PERIODS = 0.8


def _check_read_timeout(path: Path, cfg: GantryConfig, driver_options) -> None:
    """A paced loop (``loop.clock: wall``) needs the rest of the period after the read: a bus
    driver's ``timeout_s`` may be at most 0.8 of it. Unpaced runs (``virtual``) may wait longer."""
    t = getattr(driver_options, "timeout_s", None)
    period = 1.0 / cfg.loop.rate_hz
    if t is not None and cfg.loop.clock == "wall" and t > READ_TIMEOUT_MAX_PERIODS * period:
        raise ConfigError(path, "driver.timeout_s",
                          f"{t:g} s is more than {READ_TIMEOUT_MAX_PERIODS:g} of the {period:g} s period at "
                          f"{cfg.loop.rate_hz:g} Hz: a late answer would overrun the cycle; allowed: at most "
                          f"{READ_TIMEOUT_MAX_PERIODS * period:g} s with loop.clock wall, any value with "
                          f"loop.clock virtual")


def _check_command_limits(path: Path, cfg: GantryConfig, driver: Driver) -> None:
    """The controller's output limit must fit the driver's ``voltage_out`` interface: a u_lim
    above the drive's full scale would be clipped by the drive while the log records the
    unclipped value."""
    for name, ax in cfg.axes.items():
        fs = driver.voltage_limit_V(name)
        if ax.controller.u_lim > fs:
            raise ConfigError(path, f"axes.{name}.controller.u_lim",
                              f"{ax.controller.u_lim:g} V is above the {cfg.driver.type} driver's "
                              f"full scale of {fs:g} V (its voltage_out limit): the drive would "
                              f"clip what the log records; set u_lim to {fs:g} or less, or raise "
                              f"the driver's full scale")
