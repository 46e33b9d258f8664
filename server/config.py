"""Server configuration: one TOML file (scene + server settings), every key with a default that
works on loopback, validated at start with the key and the reason.

    hapticproxy serve --config scene.toml

Layout (all keys optional; ``hapticproxy serve --print-config`` prints the effective values)::

    preset = "balanced"            # fast | balanced | accurate (applied first, keys override)

    [loop]      rate_hz, spin_us ("auto" or us), realtime, cpu
    [transport] url, hmac_key_file, max_sessions, heartbeat_interval_s, silence_timeout_s
    [model]     tool, policy, contact_frame, epsilon_m, capacity, stiffness_n_per_m, damping_n_s_per_m,
                restitution, mu_static, mu_kinetic, gravity_m_per_s2, linkage_dynamics
    [controller] type, stiffness_n_per_m, damping_n_s_per_m, rot_stiffness_n_m_per_rad,
                rot_damping_n_m_s_per_rad, hand_gain, env_gain, mapping
    [safety]    max_force_n, max_torque_n_m, force_rate_n_per_s, torque_rate_n_m_per_s,
                max_speed_m_per_s, max_angular_speed_rad_per_s, watchdog_s, fade_s, ramp_in_s,
                stall_recover_s, stall_trips_max, stall_window_s
    [device]    driver (entry point name) and the driver's own keys (validated by the driver)
    [telemetry] ring_s, record, flush_rows
    [status]    address

Presets trade speed for accuracy (what each costs and buys is in ``PRESETS``, EXPERIMENTS.md
and the README): ``fast`` 512 Hz (the paper's rate), 16 contacts; ``balanced`` 1 kHz, 32
contacts; ``accurate`` 4 kHz, 64 contacts. All use the deformation policy with epsilon up to
10 mm (what a client may request).
"""
from __future__ import annotations

import copy
import difflib
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from hapticproxy.protocol.transport import parse_transport_url as parse_url

POLICIES = ("rigid", "lm0", "lm", "deformation")
CONTROLLERS = ("four_channel", "coupler", "direct")
TOOL_KINDS = ("1dof", "planar", "spatial")
#: ``model.tool`` may also be "linkage": a kinematic tree from the client's Hello, planar on a
#: planar device, spatial on a spatial one (the hand holds its held link).
MODEL_TOOLS = TOOL_KINDS + ("linkage",)
LINKAGE_DYNAMICS = ("full", "paper")
MAPPINGS = ("index", "absolute")
#: The promise for re-engaging: the first command after engaging or re-arming is at most this.
FIRST_COMMAND_MAX_N = 0.2


class ConfigError(ValueError):
    """A config value that makes no sense: ``key`` is the dotted name, ``reason`` says why."""

    def __init__(self, key: str, reason: str) -> None:
        super().__init__(f"config {key}: {reason}")
        self.key = key
        self.reason = reason


# --------------------------------------------------------------------------- value checkers
def _num(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, integer: bool = False):
    def check(key: str, v: Any) -> Any:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ConfigError(key, f"expected a number, got {v!r}")
        if integer and not (isinstance(v, int) or float(v).is_integer()):
            raise ConfigError(key, f"expected an integer, got {v!r}")
        if not math.isfinite(v):
            raise ConfigError(key, f"must be finite, got {v!r}")
        if lo is not None and (v <= lo if lo_open else v < lo):
            raise ConfigError(key, f"must be {'>' if lo_open else '>='} {lo}, got {v!r}")
        if hi is not None and v > hi:
            raise ConfigError(key, f"must be <= {hi}, got {v!r}")
        return int(v) if integer else float(v)
    return check


def _choice(options: tuple[str, ...]):
    def check(key: str, v: Any) -> str:
        if v not in options:
            raise ConfigError(key, f"expected one of {', '.join(options)}; got {v!r}")
        return v
    return check


def _bool(key: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(key, f"expected true or false, got {v!r}")
    return v


def _str(key: str, v: Any) -> str:
    if not isinstance(v, str):
        raise ConfigError(key, f"expected a string, got {v!r}")
    return v


def _vec3(key: str, v: Any) -> tuple:
    if not (isinstance(v, (list, tuple)) and len(v) == 3):
        raise ConfigError(key, f"expected 3 numbers, got {v!r}")
    return tuple(_num()(f"{key}[{i}]", x) for i, x in enumerate(v))


def _url(key: str, v: Any) -> str:
    _str(key, v)
    try:
        parse_url(v)
    except ValueError as exc:
        raise ConfigError(key, str(exc)) from None
    return v


def _spin(key: str, v: Any):
    if v == "auto":
        return v
    return _num(0, 5000)(key, v)


def _hostport(key: str, v: Any) -> str:
    _str(key, v)
    host, sep, port = v.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(key, f"expected HOST:PORT, got {v!r}")
    return v


def _cpu(key: str, v: Any) -> int:
    return _num(-1, 1023, integer=True)(key, v)


# --------------------------------------------------------------------------------- schema
#: section -> key -> (default, checker, doc). ``device`` is passed through to the driver.
SCHEMA: dict[str, dict[str, tuple[Any, Callable, str]]] = {
    "loop": {
        "rate_hz": (1000.0, _num(100, 20000), "haptic rate [Hz]; 512 is the paper's, 4000 works"),
        "spin_us": ("auto", _spin, "spin phase before each deadline [us]; auto = measured sleep overshoot"),
        "realtime": (True, _bool, "ask for SCHED_FIFO (reported in status when refused)"),
        "cpu": (-1, _cpu, "pin the loop process to this CPU (-1: no pinning)"),
    },
    "transport": {
        "url": ("udp://127.0.0.1:9870", _url, "where clients connect: udp://, zenoh://, mem://"),
        "hmac_key_file": ("", _str, "file with a shared HMAC key (hex); empty: no authentication"),
        "max_sessions": (1, _num(1, 16, integer=True), "concurrent environment clients"),
        "heartbeat_interval_s": (0.1, _num(0.001, 10, lo_open=True), "heartbeat when quiet this long"),
        "silence_timeout_s": (1.0, _num(0.01, 60, lo_open=True), "end a session silent this long (Bye 61)"),
    },
    "model": {
        "tool": ("", lambda k, v: v if v == "" else _choice(MODEL_TOOLS)(k, v),
                 "tool kind accepted from clients; empty: the device's kind; linkage: a kinematic tree "
                 "(planar on a planar device, spatial on a spatial one)"),
        "policy": ("deformation", _choice(POLICIES), "update policy (rigid = the IR baseline)"),
        "contact_frame": ("engine", _choice(("engine", "proxy")),
                          "engine: reported features taken in the engine tool's frame (ContactUpdate.tool_pose); "
                          "proxy: the paper's eq. 1, relative to the proxy's COM"),
        "epsilon_m": (0.005, _num(0, 0.1), "largest epsilon granted to clients [m]"),
        "capacity": (32, _num(1, 64, integer=True), "contacts kept by the model (granted max_contacts)"),
        "stiffness_n_per_m": (4000.0, _num(0, 1e6, lo_open=True), "local contact stiffness"),
        "damping_n_s_per_m": (30.0, _num(0, 1e4), "local contact damping"),
        "restitution": (0.0, _num(0, 1), "collision restitution"),
        "mu_static": (0.0, _num(0, 10), "static friction coefficient"),
        "mu_kinetic": (0.0, _num(0, 10), "kinetic friction coefficient"),
        "gravity_m_per_s2": ((0.0, 0.0, 0.0), _vec3, "gravity on the proxy, world"),
        "linkage_dynamics": ("full", _choice(LINKAGE_DYNAMICS),
                             "linkage proxy: full = with the Coriolis/centripetal terms (energy-consistent); "
                             "paper = neglected, the paper's eq. 7 as written"),
    },
    "controller": {
        "type": ("four_channel", _choice(CONTROLLERS), "four_channel | coupler | direct (IR baseline)"),
        "stiffness_n_per_m": (1500.0, _num(0, 1e6), "position channel, translational spring"),
        "damping_n_s_per_m": (15.0, _num(0, 1e4), "position channel, translational damper"),
        "rot_stiffness_n_m_per_rad": (1.5, _num(0, 1e4), "position channel, rotational spring"),
        "rot_damping_n_m_s_per_rad": (0.015, _num(0, 1e3), "position channel, rotational damper"),
        "hand_gain": (1.0, _num(0, 1), "force channel: measured hand wrench -> proxy"),
        "env_gain": (1.0, _num(0, 1), "force channel: environment wrench -> device"),
        "mapping": ("index", _choice(MAPPINGS),
                    "index: at engagement the device is mapped onto the proxy (no jump); "
                    "absolute: device coordinates are world coordinates"),
    },
    "safety": {
        "max_force_n": (10.0, _num(0, 1000, lo_open=True), "force cap per axis [N]"),
        "max_torque_n_m": (0.5, _num(0, 100, lo_open=True), "torque cap per axis [N m]"),
        "force_rate_n_per_s": (1000.0, _num(0, 1e6, lo_open=True), "largest force change per second"),
        "torque_rate_n_m_per_s": (50.0, _num(0, 1e5, lo_open=True), "largest torque change per second"),
        "max_speed_m_per_s": (2.0, _num(0, 100, lo_open=True), "device speed that trips a fade-out"),
        "max_angular_speed_rad_per_s": (30.0, _num(0, 1000, lo_open=True), "device angular speed that trips"),
        "watchdog_s": (0.1, _num(0.001, 10), "environment silent this long -> forces fade"),
        "fade_s": (0.2, _num(0.001, 10), "fade-out time [s]"),
        "ramp_in_s": (0.5, _num(0.001, 10), "ramp-in time after engaging or re-arming [s]"),
        "stall_recover_s": (0.5, _num(0.0, 60), "after a device-watchdog trip caused by a late loop (a stall of "
                            "the loop process), the loop must be on time this long before the force ramps back in [s]"),
        "stall_trips_max": (3, _num(0, 1000, integer=True), "more stall trips than this within stall_window_s "
                            "latch the fault until `status --rearm` (0: every stall trip latches)"),
        "stall_window_s": (60.0, _num(0.0, 86400), "window over which stall trips are counted [s]"),
    },
    "telemetry": {
        "ring_s": (10.0, _num(0.1, 600), "telemetry ring length [s]"),
        "record": ("", _str, "record telemetry to this file (empty: only on request)"),
        "flush_rows": (512, _num(16, 1 << 20, integer=True), "rows per flushed block of the recording"),
    },
    "status": {
        "address": ("127.0.0.1:9871", _hostport, "UDP address the status server answers on"),
    },
}

DEVICE_DEFAULTS = {"driver": "sim", "kind": "planar"}

#: name -> (overrides, what it costs and buys)
#: name -> (overrides, what it costs and buys). Derived from the speed / accuracy sweep
#: (``hapticproxy experiment tradeoff``, EXPERIMENTS.md): the loop's CPU is small at any rate
#: (about 8 us per step); the haptic rate buys the stable stiffness band (about proportional
#: to the rate) and smaller force steps, not wall or hole accuracy, which the environment's rate
#: and epsilon buy. Epsilon is what clients may request (the server grants at most this): 10 mm
#: catches a wall approached at 0.4 m/s from a 30-60 Hz engine more often than 5 mm, at no cost.
PRESETS: dict[str, tuple[dict, str]] = {
    "fast": ({"loop": {"rate_hz": 512.0}, "model": {"capacity": 16, "epsilon_m": 0.010}},
             "512 Hz (the paper's rate), 16 contacts, epsilon up to 10 mm: least CPU (0.4 % of a core); "
             "stable contacts up to about 10 kN/m with b = 7.5 ms x k; force steps up to 2 N per step"),
    "balanced": ({"loop": {"rate_hz": 1000.0}, "model": {"capacity": 32, "epsilon_m": 0.010}},
                 "1 kHz, 32 contacts, epsilon up to 10 mm: the default (0.8 % of a core); stable contacts "
                 "up to about 50 kN/m with b = 7.5 ms x k; force steps up to 1 N per step"),
    "accurate": ({"loop": {"rate_hz": 4000.0}, "model": {"capacity": 64, "epsilon_m": 0.010}},
                 "4 kHz, 64 contacts, epsilon up to 10 mm: 3 % of a core; stable contacts up to about "
                 "200 kN/m with b = 7.5 ms x k (1 MN/m with b = 30 N s/m); force steps up to 0.35 N per "
                 "step; wants SCHED_FIFO and a quiet core (a model update's step can outlast the 250 us period)"),
}


@dataclass(frozen=True)
class Settings:
    """Validated configuration: ``section(name)`` returns a dict of that section."""

    data: dict
    source: str = "<defaults>"

    def __getitem__(self, section: str) -> dict:
        return self.data[section]

    @property
    def rate_hz(self) -> float:
        return self.data["loop"]["rate_hz"]

    @property
    def period_ns(self) -> int:
        return int(round(1e9 / self.data["loop"]["rate_hz"]))

    @property
    def tool_kind(self) -> str:
        return self.data["model"]["tool"] or self.data["device"]["kind"]

    def as_dict(self) -> dict:
        return copy.deepcopy(self.data)


def _unknown(key: str, options) -> ConfigError:
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], list(options), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return ConfigError(key, f"unknown key{hint}")


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def defaults() -> dict:
    d = {sec: {k: spec[0] for k, spec in keys.items()} for sec, keys in SCHEMA.items()}
    d["device"] = dict(DEVICE_DEFAULTS)
    return d


def load(source: str | Path | dict | None = None, overrides: dict | None = None) -> Settings:
    """Load and validate a config (a TOML path, a dict, or ``None`` for the defaults).

    Raises :class:`ConfigError` naming the first bad key. ``overrides`` (a dict of the same
    shape) is applied last, e.g. by command-line options.
    """
    name = "<defaults>"
    if source is None:
        raw: dict = {}
    elif isinstance(source, dict):
        raw, name = copy.deepcopy(source), "<dict>"
    else:
        path = Path(source)
        name = str(path)
        try:
            raw = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError("file", f"no such file: {path}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("file", f"{path} is not valid TOML: {exc}") from None
    if overrides:
        raw = _merge(raw, overrides)
    preset = raw.pop("preset", "balanced")
    if preset not in PRESETS:
        raise ConfigError("preset", f"expected one of {', '.join(PRESETS)}; got {preset!r}")
    for sec in raw:
        if sec not in SCHEMA and sec != "device":
            raise _unknown(sec, list(SCHEMA) + ["device", "preset"])
        if not isinstance(raw[sec], dict):
            raise ConfigError(sec, f"expected a table, got {raw[sec]!r}")
    data = _merge(_merge(defaults(), PRESETS[preset][0]), raw)
    for sec, keys in SCHEMA.items():
        for k in data[sec]:
            if k not in keys:
                raise _unknown(f"{sec}.{k}", keys)
        for k, (_, check, _) in keys.items():
            data[sec][k] = check(f"{sec}.{k}", data[sec][k])
    dev = data["device"]
    if not isinstance(dev.get("driver"), str) or not dev["driver"]:
        raise ConfigError("device.driver", f"expected a driver name, got {dev.get('driver')!r}")
    if dev.get("kind") not in TOOL_KINDS:
        raise ConfigError("device.kind", f"expected one of {', '.join(TOOL_KINDS)}; got {dev.get('kind')!r}")
    data["preset"] = preset
    s = data["safety"]
    rate = data["loop"]["rate_hz"]
    if s["fade_s"] * rate < 2:
        raise ConfigError("safety.fade_s", f"{s['fade_s']} s is shorter than two haptic steps at {rate} Hz")
    first = max(s["max_force_n"], s["max_torque_n_m"]) / (s["ramp_in_s"] * rate)
    if first > FIRST_COMMAND_MAX_N:
        raise ConfigError("safety.ramp_in_s", f"{s['ramp_in_s']} s is too short for a {s['max_force_n']} N cap at "
                          f"{rate} Hz: the first command after engaging could reach {first:.3f} N "
                          f"(at most {FIRST_COMMAND_MAX_N} N)")
    if data["transport"]["silence_timeout_s"] <= data["transport"]["heartbeat_interval_s"]:
        raise ConfigError("transport.silence_timeout_s", "must exceed transport.heartbeat_interval_s")
    tool = data["model"]["tool"] or dev["kind"]
    if tool == "linkage":
        if dev["kind"] not in ("planar", "spatial"):
            raise ConfigError("model.tool", f"a linkage needs a planar or spatial device, device.kind is {dev['kind']!r}")
        if data["controller"]["type"] == "direct":
            raise ConfigError("controller.type", "direct coupling makes the device the tool, which a linkage "
                              "cannot be (the hand holds one link of a dynamic chain): use four_channel or coupler")
    elif tool != dev["kind"]:
        raise ConfigError("model.tool", f"tool kind {tool!r} does not match device.kind {dev['kind']!r}")
    return Settings(data, name)


def to_toml(data: dict) -> str:
    """Render a config dict as TOML (for ``--print-config`` and the deploy examples)."""
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {val(x)}" for k, x in v.items()) + " }"
        return repr(v)
    lines = []
    if "preset" in data:
        lines.append(f"preset = {val(data['preset'])}")
    for sec, body in data.items():
        if sec == "preset":
            continue
        lines.append(f"\n[{sec}]")
        for k, v in body.items():
            lines.append(f"{k} = {val(v)}")
    return "\n".join(lines) + "\n"
