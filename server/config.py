"""Server configuration: one TOML file (scene + server settings), every key with a default that
works on loopback, validated once at start with the key and the reason.

    hapticproxy serve --config scene.toml

Each table is declared once, as a msgspec Struct below (its keys, types, defaults, bounds and
docs); :func:`load` converts the file into them (``server/schema.py`` words the refusals:
``config loop.rate_hz: must be >= 100, got 50``, ``config loop.rtae_hz: unknown key (did you
mean 'rate_hz'?)``), then checks what spans keys: the fade and ramp against the rate, the tool
against the device, and the stable region (``server/stability.py``). ``[device]`` belongs to
the driver named by ``device.driver``: the loader asks the driver for the table's effective
values (every key of the kind, the hand's too), so a bad device key is refused here as well,
and ``hapticproxy serve --print-config`` prints every key that is in effect.

Layout (all keys optional)::

    preset = "balanced"            # fast | balanced | accurate (applied first, keys override)

    [loop]       rate_hz, spin_us ("auto" or us), realtime, cpu, clock_cpu, cpu_latency_us
    [transport]  url, hmac_key_file, max_sessions, heartbeat_interval_s, silence_timeout_s
    [model]      tool, policy, contact_frame, epsilon_m, capacity, stiffness_n_per_m,
                 damping_n_s_per_m, restitution, mu_static, mu_kinetic, gravity_m_per_s2,
                 linkage_dynamics
    [controller] type, stiffness_n_per_m, damping_n_s_per_m, rot_stiffness_n_m_per_rad,
                 rot_damping_n_m_s_per_rad, hand_gain, env_gain, mapping
    [safety]     max_force_n, max_torque_n_m, force_rate_n_per_s, torque_rate_n_m_per_s,
                 max_speed_m_per_s, max_angular_speed_rad_per_s, frozen_s, frozen_force_n, watchdog_s,
                 fade_s, ramp_in_s, stall_recover_s, stall_trips_max, stall_window_s, allow_outside_stable_region
    [passivity]  enabled, initial_budget_j, max_tank_j, low_level_j, moving_mass_kg,
                 moving_inertia_kg_m2, device_damping_n_s_per_m,
                 device_rot_damping_n_m_s_per_rad, input_credit, engine_grants, damping_credit
                 (server/passivity.py)
    [device]     driver (entry point name) and the driver's own keys (its Structs: devices/sim.py,
                 devices/remote.py, devices/hands.py for [device.hand]); the workspace mapping:
                 workspace_scale, workspace_offset_m, workspace_rotation, clutch_button,
                 clutch_ramp_s (devices/mapping.py)
    [telemetry]  ring_s, record, flush_rows
    [status]     address

Presets trade speed for accuracy (what each costs and buys is in ``PRESETS``, EXPERIMENTS.md
and the README): ``fast`` 512 Hz (the paper's rate), 16 contacts; ``balanced`` 1 kHz, 32
contacts; ``accurate`` 4 kHz, 64 contacts. All let clients request epsilon up to 40 mm (the engine told what to use).
Precedence, lowest first: the defaults, the file's ``preset``, the file's keys, a preset given
on the command line (``serve --preset``: it wins over what the file pins for the keys the
preset sets), then the other command-line options.

The stable region: contact stiffness and damping outside the region that the stable-region
sweep measured for the configured rate, controller and policy, a force-rate limit that lets one
step change the force by more than 1 N, and a spring stiffer than the device's own mass takes at
the rate (the coupling spring, or the contact with direct coupling; for drivers that report
``mass_kg``), are refused with the reason and the nearest safe value, unless ``[safety] allow_outside_stable_region = true`` (for research: the daemon logs
each such setting as a warning at start and ``status`` lists them).
"""
import copy
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import msgspec
from msgspec import Meta, Struct

from ..protocol.transport import transport_options
from ..protocol.vocab import CONTROLLERS, POLICIES  # noqa: F401 - the vocabulary, once
from ..protocol.vocab import RIGID_TOOL_KINDS as TOOL_KINDS

from . import schema
from . import stability

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


def _num(lo=None, hi=None, *, lo_open: bool = False, doc: str = "", integer: bool = False):
    """A number in [lo, hi] (``lo_open``: (lo, hi]) with its doc."""
    return Annotated[int if integer else float,
                     Meta(ge=None if lo_open else lo, gt=lo if lo_open else None, le=hi, description=doc)]


def _doc(t, doc: str):
    return Annotated[t, Meta(description=doc)]


# ---------------------------------------------------------------------------------- tables
class _Table(Struct, forbid_unknown_fields=True, kw_only=True):
    pass


class LoopConfig(_Table):
    rate_hz: _num(100, 20000, doc="haptic rate [Hz]; 512 is the paper's, 4000 works") = 1000.0
    spin_us: _doc(Union[Literal["auto"], _num(0, 5000)],
                  "spin phase before each deadline [us]; auto = measured sleep overshoot") = "auto"
    realtime: _doc(bool, "ask for SCHED_FIFO (reported in status when refused)") = True
    cpu: _num(-1, 1023, integer=True, doc="pin the loop process to this CPU (-1: no pinning)") = -1
    clock_cpu: _doc(Union[Literal["auto"], _num(-1, 1023, integer=True)],
                    "the CPU the clock thread ticks on, the loop's Python thread kept off it (with "
                    "protocol_thread); auto: the highest CPU the process may use, when it may use 2 or more; "
                    "-1: not pinned") = "auto"
    cpu_latency_us: _doc(Union[Literal["off"], _num(0, 1000, integer=True)],
                         "keep idle CPUs able to wake within this many us while the loop runs on the real "
                         "clock (Linux /dev/cpu_dma_latency, as cyclictest does; 0: idle CPUs poll instead of "
                         "halting, which halves a VM's wake-up lateness); off: the OS decides") = 0
    protocol_thread: _doc(Union[Literal["auto"], bool],
                          "the tick runs in a clock thread of its own and the protocol, the lifecycle and "
                          "housekeeping beside it, never between two ticks (a compiled device on the real clock); "
                          "auto: when the loop may run on 2 CPUs or more (not with cpu pinning it to one)") = "auto"


class TransportConfig(_Table):
    url: _doc(str, "where clients connect: udp://, zenoh://, mem:// (options in the query)") = "udp://127.0.0.1:9870"
    hmac_key_file: _doc(str, "file with a shared HMAC key (hex); empty: no authentication") = ""
    max_sessions: _num(1, 16, integer=True, doc="concurrent environment clients") = 1
    heartbeat_interval_s: _num(0.001, 10, lo_open=True, doc="heartbeat when quiet this long [s]") = 0.1
    silence_timeout_s: _num(0.01, 60, lo_open=True, doc="end a session silent this long (Bye 61) [s]") = 1.0


class ModelConfig(_Table):
    tool: _doc(Literal["", "1dof", "planar", "spatial", "linkage"],
               "tool kind accepted from clients; empty: the device's kind; linkage: a kinematic tree "
               "(planar on a planar device, spatial on a spatial one)") = ""
    policy: _doc(Literal[POLICIES], "update policy (rigid = the IR baseline)") = "deformation"
    contact_frame: _doc(Literal["engine", "proxy"],
                        "engine: reported features taken in the engine tool's frame (ContactUpdate.tool_pose); "
                        "proxy: the paper's eq. 1, relative to the proxy's COM") = "engine"
    epsilon_m: _num(0, 0.1, doc="largest epsilon granted to clients [m]") = 0.005
    capacity: _num(1, 64, integer=True, doc="contacts kept by the model (granted max_contacts)") = 32
    stiffness_n_per_m: _num(0, 1e6, lo_open=True, doc="local contact stiffness [N/m]; at most the stable "
                            "region's bound for the rate and controller (server/stability.py)") = 4000.0
    damping_n_s_per_m: _num(0, 1e4, doc="local contact damping [N s/m]; at most 7.5 ms x the stable "
                            "region's stiffness bound") = 30.0
    restitution: _num(0, 1, doc="collision restitution") = 0.0
    mu_static: _num(0, 10, doc="static friction coefficient") = 0.0
    mu_kinetic: _num(0, 10, doc="kinetic friction coefficient") = 0.0
    gravity_m_per_s2: _doc(tuple[float, float, float], "gravity on the proxy, world [m/s^2]") = (0.0, 0.0, 0.0)
    linkage_dynamics: _doc(Literal["full", "paper"],
                           "linkage proxy: full = with the Coriolis/centripetal terms (energy-consistent); "
                           "paper = neglected, the paper's eq. 7 as written") = "full"
    recovery_speed_m_per_s: _num(0, 1, doc="deformation recovery: a deformed contact the proxy rests on is "
                                 "brought back to the true geometry at up to this speed (the hand is moved out to "
                                 "the real surface); 0: off [m/s]") = 0.025
    recovery_force_rate_n_per_s: _num(0, 1e4, lo_open=True, doc="the largest rate of change of the penalty force "
                                      "the recovery adds, summed over contacts (well below the safety rate) "
                                      "[N/s]") = 200.0
    recovery_tau_s: _num(0, 10, doc="time constant of the recovery's exponential tail [s]") = 0.1
    recovery_min_age_updates: _num(0, 10000, integer=True, doc="only contacts that survived this many updates "
                                   "are recovered (an incomplete contact set is not restored)") = 10
    epsilon_prediction: _doc(bool, "tell the engine the epsilon to use next (ProxyState.epsilon_m): the "
                             "distance its tool may travel in one engine step plus its lag, at most the "
                             "granted epsilon") = True
    epsilon_floor_m: _num(0, 0.1, doc="the smallest epsilon told to an engine [m]") = 0.002
    lead: _doc(bool, "tell the engine how far to extrapolate the proxy when it tracks it (ProxyState.lead_s), "
               "measured from its tool's lag") = True
    lead_max_s: _num(0, 0.5, doc="the largest lead told [s]") = 0.1
    workspace_extent_m: _num(0.01, 1e4, doc="the scene's extent: contact positions and the engine's tool pose "
                             "within +- this of the origin on each axis, or the update is refused with an Error "
                             "naming the field (told to clients in Welcome) [m]") = 10.0
    max_constraint_speed_m_per_s: _num(0.001, 1e3, doc="largest |v_constr| an engine may report; faster is "
                                       "refused (told in Welcome) [m/s]") = 10.0
    max_separation_m: _num(0.001, 1e3, doc="largest |separation| an engine may report; more is refused "
                           "(told in Welcome) [m]") = 1.0


class ControllerConfig(_Table):
    type: _doc(Literal[CONTROLLERS], "four_channel | coupler | direct (IR baseline)") = "four_channel"
    stiffness_n_per_m: _num(0, 1e6, doc="position channel, translational spring [N/m]") = 1500.0
    damping_n_s_per_m: _num(0, 1e4, doc="position channel, translational damper [N s/m]; a heavy tool's "
                            "session gets more (stability.coupling_damping_for_tool)") = 15.0
    rot_stiffness_n_m_per_rad: _num(0, 1e4, doc="position channel, rotational spring [N m/rad]") = 1.5
    rot_damping_n_m_s_per_rad: _num(0, 1e3, doc="position channel, rotational damper [N m s/rad]; a tool "
                                    "turning heavier than the handle gets more (stability."
                                    "rot_coupling_damping_for_tool)") = 0.015
    hand_gain: _num(0, 1, doc="force channel: measured hand wrench -> proxy") = 1.0
    env_gain: _num(0, 1, doc="force channel: environment wrench -> device") = 1.0
    mapping: _doc(Literal["index", "absolute"],
                  "index: at engagement the device is mapped onto the proxy (no jump); "
                  "absolute: device coordinates are world coordinates") = "index"


class SafetyConfig(_Table):
    max_force_n: _num(0, 1000, lo_open=True, doc="cap on the force's norm [N] (the device's own cap applies too)") = 10.0
    max_torque_n_m: _num(0, 100, lo_open=True, doc="cap on the torque's norm [N m]") = 0.5
    force_rate_n_per_s: _doc(Union[Literal["auto"], _num(0, 1e6, lo_open=True)],
                             "largest force change per second [N/s]; at most 1 N x rate_hz, so one haptic "
                             "step never changes the force by more than 1 N (a larger step is felt as a "
                             "kick: 1e6 N/s let a 9.5 N step through); auto = min(1000, 1 N x rate_hz)") = "auto"
    torque_rate_n_m_per_s: _num(0, 1e5, lo_open=True, doc="largest torque change per second [N m/s]") = 50.0
    max_speed_m_per_s: _num(0, 100, lo_open=True, doc="device speed that trips a fade-out [m/s]") = 2.0
    max_angular_speed_rad_per_s: _num(0, 1000, lo_open=True, doc="device angular speed that trips [rad/s]") = 30.0
    frozen_s: _num(0, 10, doc="the device's position bit-identical this long while at least frozen_force_n is "
                   "commanded: a stuck sensor, cut as a device fault (0: off; a handle held against its "
                   "mechanical stop trips too) [s]") = 0.5
    frozen_force_n: _num(0, 100, doc="the force a command needs for frozen_s to count (0: 0.25 N or a quarter of "
                         "the force cap, whichever is lower) [N]") = 0.0
    watchdog_s: _num(0.001, 10, doc="environment silent this long -> forces fade [s]") = 0.1
    fade_s: _num(0.001, 10, doc="fade-out time [s]") = 0.2
    ramp_in_s: _num(0.001, 10, doc="ramp-in time after engaging or re-arming [s]") = 0.5
    stall_recover_s: _num(0.0, 60, doc="after a device-watchdog trip caused by a late loop (a stall of the "
                          "loop process), the loop must be on time this long before the force ramps back in [s]") = 0.5
    stall_trips_max: _num(0, 1000, integer=True, doc="more stall trips than this within stall_window_s latch the "
                          "fault until `status --rearm` (0: every stall trip latches)") = 3
    stall_window_s: _num(0.0, 86400, doc="window over which stall trips are counted [s]") = 60.0
    allow_outside_stable_region: _doc(bool, "research only: accept contact stiffness, damping and force rate "
                                      "outside the measured stable region (logged as a warning at start, "
                                      "listed by status)") = False


class PassivityConfig(_Table):
    """The passivity layer under the controller (``server/passivity.py``: an energy tank at the
    hand's port that limits the command when it runs short)."""
    enabled: _doc(bool, "limit the command when the tank runs short (off: the tank is only accounted, in "
                  "status and telemetry). On by default: on the project's own scenes without delay it acts on no "
                  "step (EXPERIMENTS.md, transparency)") = True
    initial_budget_j: _num(0, 10, doc="the tank at start: energy the server may give the hand beyond what the "
                           "hand put in [J]") = 0.01
    max_tank_j: _num(0, 100, doc="the tank's cap: what a hand's input can store for later; the deformation "
                     "recovery pays from it (a 1 N push 30 mm past a late wall: 30 mJ to lift the hand back) [J]") = 0.2
    low_level_j: _num(0, 10, lo_open=True, doc="below this level the command is limited, smoothly, fully at an "
                      "empty tank [J]") = 0.005
    moving_mass_kg: _num(0, 1e3, doc="the moving mass at the handle the layer predicts the next period's work "
                         "with (0: the device's stated figure, else 0.02 kg: lighter predicts more, limits more) "
                         "[kg]") = 0.0
    moving_inertia_kg_m2: _num(0, 10, doc="the smallest principal moment of inertia at the handle, alike (0: the "
                               "device's, else 1e-6) [kg m^2]") = 0.0
    device_damping_n_s_per_m: _num(0, 1e4, doc="the device's physical viscous damping, as its maker states it: "
                                   "what it dissipates feeds the tank (0: the device's stated figure, a simulated "
                                   "device's own; none stated: nothing assumed) [N s/m]") = 0.0
    device_rot_damping_n_m_s_per_rad: _num(0, 1e3, doc="and its rotational damping, alike [N m s/rad]") = 0.0
    input_credit: _num(0, 1, lo_open=True, doc="the share of the energy the hand puts in that the tank keeps "
                       "(1: lossless, an undamped bounce keeps bouncing; below 1 the layer dissipates the rest, "
                       "and an exchange that gives back what it took dies out). 1 with the 10 mJ budget (the "
                       "default): the project's scenes untouched, a late engine's recovery does its work. For "
                       "a device with little or unknown damping (no maker's figure) and stiff walls: 0.45 with "
                       "initial_budget_j = 0.002 settles undamped walls at 5x the Colgate-Schenkel bound within "
                       "1 s, but holds back the recovery on a delayed active scene, and a device that states no "
                       "damping approaches a wall a little later (the four-channel controller's free-motion "
                       "push is withheld sooner: EXPERIMENTS.md, passivity)") = 1.0
    engine_grants: _doc(bool, "add the work an engine declares it does on the tool (ContactUpdate."
                        "work_on_tool_j) to the tank") = True
    damping_credit: _num(0, 1, doc="the share of what the device's damping dissipates that feeds the tank (1: "
                         "all, the most transparent: free motion costs the tank nothing; 0.5: the layer also stops "
                         "a limit cycle beyond the device's bound that its damper absorbs, every direct-coupling "
                         "z-width panel a quarter to a half wider, a late wall's recovery limited on ~4 % of steps; "
                         "0: a little wider still, Fig. 14's approach limited on 7 %: EXPERIMENTS.md, z-width)") = 1.0


class TelemetryConfig(_Table):
    ring_s: _num(0.1, 600, doc="telemetry ring length [s]") = 10.0
    record: _doc(str, "record telemetry to this file (empty: only on request)") = ""
    flush_rows: _num(16, 1 << 20, integer=True, doc="rows per flushed block of the recording") = 512


class StatusConfig(_Table):
    address: _doc(str, "UDP address the status server answers on (HOST:PORT)") = "127.0.0.1:9871"


class DeviceHeader(Struct, kw_only=True):
    """The keys of ``[device]`` the server reads itself; the rest is the driver's."""
    driver: _doc(Annotated[str, Meta(min_length=1)], "device driver (a built-in or a hapticproxy.devices entry point; `hapticproxy plugins`)") = "sim"
    kind: _doc(Literal["1dof", "planar", "spatial"], "1dof | planar | spatial") = "planar"


class ServerConfig(_Table):
    """The whole file."""
    preset: _doc(Literal["fast", "balanced", "accurate"], "fast | balanced | accurate (keys override it)") = "balanced"
    loop: LoopConfig = msgspec.field(default_factory=LoopConfig)
    transport: TransportConfig = msgspec.field(default_factory=TransportConfig)
    model: ModelConfig = msgspec.field(default_factory=ModelConfig)
    controller: ControllerConfig = msgspec.field(default_factory=ControllerConfig)
    safety: SafetyConfig = msgspec.field(default_factory=SafetyConfig)
    passivity: PassivityConfig = msgspec.field(default_factory=PassivityConfig)
    device: dict = msgspec.field(default_factory=dict)
    telemetry: TelemetryConfig = msgspec.field(default_factory=TelemetryConfig)
    status: StatusConfig = msgspec.field(default_factory=StatusConfig)


SECTIONS = ("loop", "transport", "model", "controller", "safety", "passivity", "device", "telemetry", "status")
DEVICE_DEFAULTS = {"driver": "sim", "kind": "planar"}
#: dotted key -> doc, for ``--print-config``
DOCS = schema.descriptions(ServerConfig)
DOCS.update({f"device.{k}": v for k, v in schema.descriptions(DeviceHeader).items()})

#: name -> (overrides, what it costs and buys). Derived from the speed / accuracy sweep
#: (``hapticproxy experiment tradeoff``, EXPERIMENTS.md): the loop's CPU is small at any rate
#: (about 8 us per step); the haptic rate buys the stable stiffness band (about proportional
#: to the rate) and smaller force steps, not wall or hole accuracy, which the environment's rate
#: and epsilon buy. Epsilon is what clients may request (the server grants at most this): with
#: the server telling the engine the epsilon to use next (model.epsilon_prediction) a large cap
#: costs nothing at rest, and 40 mm lets the prediction catch a fast approach; with recovery and
#: advice on, the wall is felt where it is within about 0.27 s of contact at every rate
#: (EXPERIMENTS.md, ``hapticproxy experiment tradeoff``).
PRESETS: dict[str, tuple[dict, str]] = {
    "fast": ({"loop": {"rate_hz": 512.0}, "model": {"capacity": 16, "epsilon_m": 0.040}},
             "512 Hz (the paper's rate), 16 contacts, epsilon up to 40 mm (the engine told what to use): least CPU (0.4 % of a core); "
             "stable contacts up to about 10 kN/m with b = 7.5 ms x k; force steps limited to 1 N per step (the "
             "default force rate at 512 Hz is 512 N/s; the sweep's 1.95 N steps were measured at 1000 N/s)"),
    "balanced": ({"loop": {"rate_hz": 1000.0}, "model": {"capacity": 32, "epsilon_m": 0.040}},
                 "1 kHz, 32 contacts, epsilon up to 40 mm (the engine told what to use): the default (0.8 % of a core); stable contacts "
                 "up to about 50 kN/m with b = 7.5 ms x k; force steps up to 1 N per step"),
    "accurate": ({"loop": {"rate_hz": 4000.0}, "model": {"capacity": 64, "epsilon_m": 0.040}},
                 "4 kHz, 64 contacts, epsilon up to 40 mm (the engine told what to use): 3 % of a core; stable contacts up to about "
                 "200 kN/m with b = 7.5 ms x k (1 MN/m with b = 30 N s/m); force steps up to 0.35 N per "
                 "step; wants SCHED_FIFO and a quiet core (a model update's step can outlast the 250 us period)"),
}


@dataclass(frozen=True)
class Settings:
    """Validated configuration: ``settings["model"]["policy"]`` is a plain dict of that table.

    ``outside_stable_region``: the settings that are outside the measured stable region and were
    accepted because ``safety.allow_outside_stable_region`` is set, as ``(key, reason)``.
    ``given``: the dotted keys the file or the command line set (the rest are defaults, which
    ``devices/safe.py`` may lower to what the device takes); ``lowered``: the defaults it
    lowered, as ``(key, was, now, reason)``."""

    data: dict
    source: str = "<defaults>"
    outside_stable_region: tuple = ()
    given: frozenset = frozenset()
    lowered: tuple = ()

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

    def to_toml(self) -> str:
        """Every key in effect as TOML, each with its doc (``serve --print-config``)."""
        return to_toml(self.data)


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _fail(key: str, reason: str) -> ConfigError:
    return ConfigError(key, reason)


def defaults() -> dict:
    """The tables as the Structs declare them (no preset applied)."""
    d = schema.builtins(ServerConfig())
    d.pop("preset")
    d["device"] = dict(DEVICE_DEFAULTS)
    return d


def _preset(name: Any, key: str = "preset") -> dict:
    if not isinstance(name, str) or name not in PRESETS:
        raise ConfigError(key, f"expected one of {', '.join(PRESETS)}; got {name!r}")
    return PRESETS[name][0]


def _read(source) -> tuple[dict, str]:
    if source is None:
        return {}, "<defaults>"
    if isinstance(source, dict):
        return copy.deepcopy(source), "<dict>"
    path = Path(source)
    try:
        return tomllib.loads(path.read_text()), str(path)
    except FileNotFoundError:
        raise ConfigError("file", f"no such file: {path}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("file", f"{path} is not valid TOML: {exc}") from None


def load(source: str | Path | dict | None = None, overrides: dict | None = None) -> Settings:
    """Load and validate a config (a TOML path, a dict, or ``None`` for the defaults).

    Raises :class:`ConfigError` naming the first bad key. ``overrides`` (a dict of the same
    shape, e.g. from command-line options) is applied last; a ``preset`` in it wins over the
    file's keys for the keys that preset sets (module docstring: precedence).
    """
    raw, name = _read(source)
    over = copy.deepcopy(overrides or {})
    cli_preset = over.pop("preset", None)
    merged = _merge(_preset(raw.get("preset", "balanced")), raw)
    if cli_preset is not None:
        merged = _merge(merged, _preset(cli_preset, "preset"))
        merged["preset"] = cli_preset
    merged = _merge(merged, over)
    merged.setdefault("device", {})
    if isinstance(merged["device"], dict):
        merged["device"] = {**DEVICE_DEFAULTS, **merged["device"]}
    cfg = schema.convert(ServerConfig, merged, prefix="", fail=_fail)
    hdr = schema.convert(DeviceHeader, {k: cfg.device[k] for k in ("driver", "kind") if k in cfg.device},
                         prefix="device", fail=_fail)
    s = cfg.safety
    rate = cfg.loop.rate_hz
    if s.force_rate_n_per_s == "auto":
        s.force_rate_n_per_s = min(1000.0, stability.max_force_rate_n_per_s(rate))
    try:
        transport_options(cfg.transport.url)
    except ValueError as exc:
        raise ConfigError("transport.url", str(exc)) from None
    _hostport("status.address", cfg.status.address)
    if s.fade_s * rate < 2:
        raise ConfigError("safety.fade_s", f"{s.fade_s} s is shorter than two haptic steps at {rate} Hz")
    first = max(s.max_force_n, s.max_torque_n_m) / (s.ramp_in_s * rate)
    if first > FIRST_COMMAND_MAX_N:
        raise ConfigError("safety.ramp_in_s", f"{s.ramp_in_s} s is too short for a {s.max_force_n} N cap at "
                          f"{rate} Hz: the first command after engaging could reach {first:.3f} N "
                          f"(at most {FIRST_COMMAND_MAX_N} N)")
    if cfg.transport.silence_timeout_s <= cfg.transport.heartbeat_interval_s:
        raise ConfigError("transport.silence_timeout_s", "must exceed transport.heartbeat_interval_s")
    pas = cfg.passivity
    if pas.initial_budget_j > pas.max_tank_j:
        raise ConfigError("passivity.initial_budget_j", f"{pas.initial_budget_j} J is more than passivity.max_tank_j "
                          f"({pas.max_tank_j} J): raise max_tank_j or lower the budget")
    if pas.low_level_j > pas.max_tank_j:
        raise ConfigError("passivity.low_level_j", f"{pas.low_level_j} J is more than passivity.max_tank_j "
                          f"({pas.max_tank_j} J): the tank could never leave the limited range")
    tool = cfg.model.tool or hdr.kind
    if tool == "linkage":
        if hdr.kind not in ("planar", "spatial"):
            raise ConfigError("model.tool", f"a linkage needs a planar or spatial device, device.kind is {hdr.kind!r}")
        if cfg.controller.type == "direct":
            raise ConfigError("controller.type", "direct coupling makes the device the tool, which a linkage "
                              "cannot be (the hand holds one link of a dynamic chain): use four_channel or coupler")
    elif tool != hdr.kind:
        raise ConfigError("model.tool", f"tool kind {tool!r} does not match device.kind {hdr.kind!r}")
    outside = stability.outside_stable_region(
        rate_hz=rate, controller=cfg.controller.type, policy=cfg.model.policy,
        stiffness_n_per_m=cfg.model.stiffness_n_per_m, damping_n_s_per_m=cfg.model.damping_n_s_per_m,
        force_rate_n_per_s=s.force_rate_n_per_s)
    device = device_config(cfg.device, period_s=int(round(1e9 / rate)) * 1e-9)
    mass = device.get("mass_kg")
    outside += stability.above_device_limits(
        rate_hz=rate, controller=cfg.controller.type, device_mass_kg=mass if isinstance(mass, (int, float)) else None,
        stiffness_n_per_m=cfg.model.stiffness_n_per_m, coupling_stiffness_n_per_m=cfg.controller.stiffness_n_per_m)
    if outside and not s.allow_outside_stable_region:
        key, why = outside[0]
        raise ConfigError(key, f"{why}; or set safety.allow_outside_stable_region = true (research only)")
    data = schema.builtins(cfg)
    data["device"] = device
    preset = data.pop("preset")
    data = {"preset": preset, **data}
    return Settings(data, name, tuple(outside), frozenset(_dotted(raw)) | frozenset(_dotted(over)))


def _dotted(table: dict, prefix: str = ""):
    """The dotted keys of a nested table (its leaves; ``preset`` left out: its values are defaults)."""
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and key != "device.hand":
            yield from _dotted(v, key + ".")
        elif key != "preset":
            yield key


def _hostport(key: str, v: str) -> None:
    host, sep, port = v.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(key, f"expected HOST:PORT, got {v!r}")


def device_config(table: dict, *, period_s: float) -> dict:
    """The ``[device]`` table with the driver's effective values (every key of the kind, the
    hand's too), from the driver's ``effective_config`` hook (an attribute of the registered
    factory: ``factory.effective_config(table, period_s=...) -> dict``, raising
    ``ValueError("device.<key>: ...")``). A driver without the hook validates its table when it
    is built; its table is passed on as written."""
    from .devices import mapping
    from .devices.base import device_factory

    try:
        factory = device_factory(table["driver"])
    except ValueError as exc:
        raise ConfigError("device.driver", str(exc).removeprefix("device.driver: ")) from None
    # the workspace mapping's keys are the server's (devices/mapping.py), the rest the driver's
    table, asked = mapping.split(copy.deepcopy(table))
    hook = getattr(factory, "effective_config", None)
    try:
        out = copy.deepcopy(table) if hook is None else hook(table, period_s=period_s)
        kind = out.get("kind", table.get("kind", "planar"))
        m, _ = mapping.parse_mapping(asked, kind=kind, period_s=period_s)
    except ConfigError:
        raise
    except ValueError as exc:
        key, sep, why = str(exc).partition(": ")
        if sep and key.startswith("device"):
            raise ConfigError(key, why) from None
        raise ConfigError("device", str(exc)) from None
    if asked:  # printed when the config names them (a table without them maps nothing)
        out.update(mapping.effective(m))
    return out


def to_toml(data: dict) -> str:
    """Render a config dict as TOML, each key with its doc (``--print-config``, the deploy
    examples). Loading the text gives the same settings."""
    return schema.to_toml(data, DOCS)
