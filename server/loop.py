"""The haptic loop: a fixed-rate schedule of ack/update -> poll -> read -> control+model -> write.

``HapticLoop`` knows no engine and no particular device: it owns a transport (any backend), the
protocol's ``ServerEndpoint``, a device driver, the controller/safety arrays and, once a client
has engaged it, a ``LocalModel`` built from the client's ``Hello``. Each step, in this order:

1. wait for the absolute deadline (``deadline += period_ns``; the clock is injected);
2. if the previous step applied a ContactUpdate: acknowledge it with a ``ProxyState``; if it
   received one: update the local model (receiving, applying and acknowledging an update fall in
   three consecutive steps, so no step pays for two of them while updates come at most every
   other step);
3. poll the transport without blocking (at most ``max_packets_per_step`` datagrams and at most
   ``POLL_BUDGET`` of the period, so a flood cannot stretch a step, even of datagrams that are
   slow to refuse); the session layer keeps the newest ContactUpdate for the next step;
4. read the device;
5. run the controller, the model step and the safety filter (one numba kernel);
6. write the device command;
7. account: lateness, compute time, telemetry row (one numba kernel, no allocation).

What a step costs in objects: the numba kernels (controller + model + safety, accounting, the
simulated device) allocate nothing and touch only preallocated arrays. The Python that strings
them together creates a few short-lived small objects per step (the poll's result tuple, ints),
all freed at once by reference counting; the collector is frozen and disabled in the loop
process, so nothing ever pauses to collect (a test checks that steps leave no memory behind).
Only the arrival of a datagram costs a copy of it and its decode, and only an accepted
ContactUpdate costs the model update and the ProxyState encode (at the engine's 30-60 Hz).

Every ``housekeeping_s`` (10 ms) it also runs the session timers (heartbeats, timeouts), the
supervisor's requests (stop, re-arm) and publishes its counters to the shared status block.

Loop states and their transitions: ``lifecycle`` (one table; ``HapticLoop.transition`` is the
only place that changes the state).
"""
from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

from ..protocol.vocab import JOINT_TYPE_NAMES, TOOL_KIND_NAMES, TOOL_KINDS_BY_NAME
from ..protocol.codec import Codec
from ..protocol.session import ServerConfig, ServerEndpoint

from . import control as ctl
from . import egress, ingest, tick
from .devices import safe
from .devices.base import (
    DEV_FAULT_LINK, DEV_FAULT_NAMES, DEV_FAULT_WATCHDOG, DEV_NSTATE, DS_BUTTONS, DS_TIME, empty_state, load_device,
)
from .lifecycle import LOOP_STATES, LS, SERVER_STATE_BY_CODE, STALL_EXPLAINS_S, TRANSITIONS, Fault, Reason
from .prediction import EngineAdvice, advice_update, tool_radius_m, warm_up as advice_warm_up
from .model.layout import K_M
from .model.model import ContactParams, LinkSpec, LocalModel, ToolSpec, warm_up as model_warm_up
from .readonly import frozen_copies
from .rings import account, record_contacts
from .shm import CT, ST, SharedState

#: status slots that show one of the endpoint's counters as it is: (slot, counter attribute)
_ENDPOINT_STATUS = tuple((ST[slot], attr) for slot, attr in (
    ("decode_errors", "decode_errors"), ("sessions_opened", "sessions_opened"),
    ("datagrams_received", "received"), ("bad_token", "bad_token"), ("wrong_peer", "wrong_peer"),
    ("unknown_session", "unknown_session"), ("bad_mac", "bad_mac"), ("unexpected", "unexpected"),
    ("rejects_sent", "rejects_sent"), ("refused_out_of_bounds", "out_of_bounds"),
    ("refused_unusable", "unusable"), ("refused_seq_jump", "seq_jump")))

#: Share of the period the poll may spend reading datagrams before it leaves the rest for the
#: next step. Refusing a datagram usually costs 2-6 us, but a 1 kB msgpack of 1,000 nested
#: arrays costs ~40 us to unpack and refuse: 32 of them per step stretched steps to milliseconds
#: (measured with ``tests/faults``), so the count bound alone does not bound the time.
POLL_BUDGET = 0.25

WD_OK = 0
WD_SILENT = 1
WD_SESSION_ENDED = 2

#: updates over which the environment's rate is measured (``HapticLoop._track_env``)
ENV_RATE_WINDOW = 32
#: steps housekeeping may wait for a step that handles no update (receives or applies one)
_HK_MAX_DEFER = 3
#: the tick's device arrays for a device that is not simulated, and its linkage arrays for a
#: rigid tool (never read: the same types as the real ones, so one compiled tick serves all)
_NO_SIM_DEVICE = (np.zeros(1), np.zeros(1), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64), np.zeros(1),
                  np.zeros((1, 1)), np.zeros(1), np.zeros(6))
_NO_LINKAGE = (np.zeros(8, dtype=np.int64), np.zeros((1, 1)), np.zeros((1, 1), dtype=np.int64), np.zeros((1, 1)))
#: datagrams start() discards at most (what a socket buffer holds of small ones)
_START_DRAIN_MAX = 100_000


def tool_from_hello(hello, planar: bool | None = None) -> ToolSpec:
    """The proxy's ToolSpec from a client's Hello; the hand holds a rigid tool at its tool-frame
    origin, a linkage at its held link's frame origin. ``planar``: a linkage's model (planar on a
    planar device, spatial on a spatial one); ``ValueError`` naming the field for a linkage the
    model cannot hold."""
    kind = TOOL_KIND_NAMES.get(hello.tool_kind)
    if kind is None:
        raise ValueError(f"tool_kind {hello.tool_kind!r} is not a tool this server models")
    if kind == "linkage":
        if planar is None:
            raise ValueError("tool_kind: a linkage needs a planar or spatial device")
        links = []
        for ln in hello.links:
            ixx, iyy, izz, ixy, ixz, iyz = (float(v) for v in ln["inertia_kg_m2"])
            origin = tuple(float(v) for v in ln["joint_origin"])
            links.append(LinkSpec(
                float(ln["mass_kg"]), tuple(float(v) for v in ln["com_m"]),
                ((ixx, ixy, ixz), (ixy, iyy, iyz), (ixz, iyz, izz)), int(ln["parent"]),
                JOINT_TYPE_NAMES.get(int(ln["joint_type"]), "?"), tuple(float(v) for v in ln["joint_axis"]),
                origin[:3], origin[3:7] if int(ln["parent"]) >= 0 else (1.0, 0.0, 0.0, 0.0)))
        tool = ToolSpec.linkage(links, int(hello.held_link), planar)
        tool.validated()
        return tool
    com = np.asarray(hello.com_m, dtype=float)
    ixx, iyy, izz, ixy, ixz, iyz = (float(v) for v in hello.inertia_kg_m2)
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    if kind == "1dof":
        return ToolSpec("1dof", float(hello.mass_kg), axis=tuple(float(a) for a in hello.axis),
                        hand_point_m=tuple(-com))
    if kind == "planar":
        return ToolSpec.planar(float(hello.mass_kg), izz, hand_point_m=tuple(-com[:2]))
    return ToolSpec.spatial(float(hello.mass_kg), inertia, hand_point_m=tuple(-com))

def q_from_tool_pose(kind: str, pose, com_m, axis=None, joints=None) -> np.ndarray:
    """COM configuration q of the proxy from the engine's tool-frame pose (x y z qw qx qy qz).
    ``kind`` "linkage-planar" / "linkage-spatial": the root frame's pose coordinates (no COM
    shift) followed by ``joints``.

    Plain floats on purpose: it runs once per model update inside a haptic step."""
    px, py, pz = float(pose[0]), float(pose[1]), float(pose[2])
    w, x, y, z = float(pose[3]), float(pose[4]), float(pose[5]), float(pose[6])
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n > 0:
        w, x, y, z = w / n, x / n, y / n, z / n
    else:
        w, x, y, z = 1.0, 0.0, 0.0, 0.0
    if kind == "linkage-planar":
        return np.r_[px, py, 2 * math.atan2(z, w), joints]
    if kind == "linkage-spatial":
        return np.r_[px, py, pz, w, x, y, z, joints]
    cx, cy, cz = float(com_m[0]), float(com_m[1]), float(com_m[2])
    if kind == "1dof":
        ax = axis if axis is not None else (1.0, 0.0, 0.0)
        return np.array([(px + cx) * ax[0] + (py + cy) * ax[1] + (pz + cz) * ax[2]])
    # c = p + R com
    rx = (1 - 2 * (y * y + z * z)) * cx + 2 * (x * y - w * z) * cy + 2 * (x * z + w * y) * cz
    ry = 2 * (x * y + w * z) * cx + (1 - 2 * (x * x + z * z)) * cy + 2 * (y * z - w * x) * cz
    rz = 2 * (x * z - w * y) * cx + 2 * (y * z + w * x) * cy + (1 - 2 * (x * x + y * y)) * cz
    if kind == "planar":
        return np.array([px + rx, py + ry, 2 * math.atan2(z, w)])
    return np.array([px + rx, py + ry, pz + rz, w, x, y, z])

class ModelFactory:
    """Builds the local model for a client's Hello: the server's contact parameters, rate and
    policy; the tool from the Hello. The handshake's check builds it (a Hello the model cannot
    hold is refused by name) and keeps it for the engagement that follows, so an engagement
    never builds a second one."""

    KEEP = 4  # models kept from recent Hello checks (one per concurrent handshake is plenty)

    def __init__(self, settings, device_kind: str, period_s: float) -> None:
        mcfg = settings["model"]
        self.settings = settings
        self.device_kind = device_kind
        self.period_s = float(period_s)
        self.linkage = settings.tool_kind == "linkage"
        self.contact = ContactParams(
            stiffness_n_per_m=mcfg["stiffness_n_per_m"], damping_n_s_per_m=mcfg["damping_n_s_per_m"],
            restitution=mcfg["restitution"], mu_static=mcfg["mu_static"], mu_kinetic=mcfg["mu_kinetic"])
        self._kept: list[tuple[object, tuple, tuple]] = []  # (hello, (eps, max_contacts), (tool, model))

    def build(self, hello, epsilon_m: float, max_contacts: int):
        """(tool, LocalModel) for ``hello``; ValueError naming the field when it cannot be modelled."""
        mcfg = self.settings["model"]
        tool = tool_from_hello(hello, planar=(self.device_kind == "planar") if self.linkage else None)
        eps = 0.0 if mcfg["policy"] == "lm0" else float(epsilon_m)
        model = LocalModel(tool, self.contact, period_s=self.period_s, policy=mcfg["policy"], epsilon_m=eps,
                           capacity=mcfg["capacity"], gravity_m_per_s2=mcfg["gravity_m_per_s2"],
                           max_update_contacts=max(mcfg["capacity"], int(max_contacts)),
                           linkage_dynamics=mcfg["linkage_dynamics"],
                           recovery_speed_m_per_s=mcfg["recovery_speed_m_per_s"],
                           recovery_force_rate_n_per_s=mcfg["recovery_force_rate_n_per_s"],
                           recovery_tau_s=mcfg["recovery_tau_s"],
                           recovery_min_age_updates=mcfg["recovery_min_age_updates"], warm=False)
        return tool, model

    def check(self, hello, epsilon_m: float, max_contacts: int) -> str:
        """"" if the model can hold ``hello``'s tool (the model is kept for :meth:`take`), else why not."""
        try:
            built = self.build(hello, epsilon_m, max_contacts)
        except ValueError as exc:
            return str(exc)
        self._kept = [k for k in self._kept if k[0] is not hello][-(self.KEEP - 1):] + [
            (hello, (float(epsilon_m), int(max_contacts)), built)]
        return ""

    def take(self, hello, epsilon_m: float, max_contacts: int):
        """The model the check built for this Hello with these grants, or a new one."""
        key = (float(epsilon_m), int(max_contacts))
        for i, (h, k, built) in enumerate(self._kept):
            if h is hello and k == key:
                del self._kept[i]
                return built
        return self.build(hello, epsilon_m, max_contacts)

class HapticLoop:
    """The server loop. It receives its parts built (``HapticLoop.build`` builds them from the
    settings) and checks at construction that they fit each other: the device's kind is the one
    the settings model, the controller was made for that device, the transport can be polled.
    ``run()``, or ``step()`` by hand in tests.

    Every change of ``state`` goes through :meth:`transition` (the table is
    ``lifecycle.TRANSITIONS``)."""

    @classmethod
    def build(cls, settings, *, clock=None, transport=None, device=None, shared: SharedState | None = None,
              hmac_key: bytes | None = None, **kw) -> "HapticLoop":
        """Open what is not given (the transport at ``transport.url``, the ``[device]`` driver); the
        loop closes what it opened."""
        from ..protocol.transport import open_transport

        from .clock import MonotonicClock

        clock = clock or MonotonicClock()
        own_t = transport is None
        own_d = device is None
        if own_t:
            transport = open_transport(settings["transport"]["url"], "server")
        try:
            if own_d:
                device = load_device(settings["device"]["driver"], dict(settings["device"]),
                                     period_s=settings.period_ns * 1e-9, clock_ns=clock.now_ns)
            # the gains the device renders stably at this rate (devices/safe.py): defaults
            # lowered, a set value beyond them refused (ConfigError) unless the override is on
            derived = safe.derive(settings, device.info)
            safe.log_derived(settings, derived)
            loop = cls(derived, clock=clock, transport=transport, device=device, shared=shared, hmac_key=hmac_key,
                       **kw)
        except BaseException:
            if own_t:
                transport.close()
            if own_d and device is not None:
                device.close()
            raise
        loop._owns_transport, loop._owns_device = own_t, own_d
        return loop

    def __init__(self, settings, *, transport, device, clock=None, shared: SharedState | None = None,
                 endpoint: ServerEndpoint | None = None, controller: ctl.Controller | None = None,
                 models: ModelFactory | None = None, hmac_key: bytes | None = None,
                 max_packets_per_step: int = 32) -> None:
        from .clock import MonotonicClock

        self.settings = settings
        self.period_ns = settings.period_ns
        self.dt_s = self.period_ns * 1e-9
        self.clock = clock or MonotonicClock()
        self.kind = settings.tool_kind
        self.max_packets_per_step = int(max_packets_per_step)
        self.poll_budget_ns = int(POLL_BUDGET * settings.period_ns)
        self.poll_cut = 0  # steps whose poll stopped at the time budget (datagrams left for later)
        self.shared = shared or SharedState.local(max(16, int(settings["telemetry"]["ring_s"] * settings.rate_hz)))
        # the parts, checked against each other
        want = settings["device"]["kind"] if self.kind == "linkage" else self.kind
        if getattr(device, "kind", None) != want:
            raise ValueError(f"device: the loop models a {self.kind} tool on a {want} device, got a "
                             f"{getattr(device, 'kind', '?')} device")
        for name in ("recv_into", "send", "max_packet_bytes", "counters"):
            if not hasattr(transport, name):
                raise ValueError(f"transport: {type(transport).__name__} has no {name}")
        self.transport = transport
        self.device = device
        self._owns_transport = False
        self._owns_device = False
        self.models = models or ModelFactory(settings, device.kind, self.dt_s)
        tcfg = settings["transport"]
        mcfg = settings["model"]
        scfg = settings["safety"]
        self.server_config = ServerConfig(
            haptic_rate_hz=settings.rate_hz,
            max_epsilon_m=0.0 if mcfg["policy"] == "lm0" else mcfg["epsilon_m"],
            max_contacts=mcfg["capacity"],
            heartbeat_interval_s=tcfg["heartbeat_interval_s"],
            silence_timeout_s=tcfg["silence_timeout_s"],
            max_sessions=tcfg["max_sessions"],
            supported_tools=frozenset({TOOL_KINDS_BY_NAME[self.kind]}),
            hello_check=self._check_hello,
            workspace_extent_m=mcfg["workspace_extent_m"],
            max_constraint_speed_m_per_s=mcfg["max_constraint_speed_m_per_s"],
            max_separation_m=mcfg["max_separation_m"],
            update_watchdog_s=scfg["watchdog_s"],
        )
        # the protocol's value rules, vouched for by kernels (``ingest``: a session's updates read
        # and checked whole by one call) and the ProxyState packed by one (``egress``): receiving
        # and acknowledging an update cost a kernel call each instead of dozens of Python and
        # numpy calls. Both read and write little-endian float64 bytes as the wire has them.
        self.endpoint = endpoint or ServerEndpoint(
            self.transport.send, self.server_config, hmac_key=hmac_key,
            codec=Codec(self.server_config.limits, contact_check=ingest.contacts_surely_valid,
                        proxy_state_packer=(egress.ProxyStatePacker(self.server_config.limits.max_links)
                                            if sys.byteorder == "little" else None)),
            update_check=ingest.update_surely_in_bounds,
            update_parser=ingest.ContactParser(self.server_config.limits) if sys.byteorder == "little" else None)
        self.ctrl = controller or ctl.Controller(settings, self.device.kind, self.device.limits)
        if self.ctrl.device_kind != self.device.kind:
            raise ValueError(f"controller: made for a {self.ctrl.device_kind} device, the device is {self.device.kind}")
        self._index_mapping = settings["controller"]["mapping"] == "index"
        #: a linkage tool is engaged: the step runs ``control.haptic_step_linkage``
        self._linkage = False
        self._largs = None
        self.dev = empty_state()
        self.rxbuf = bytearray(self.transport.max_packet_bytes)
        # model state (set when a client engages)
        self.model: LocalModel | None = None
        self._margs = None
        self.session_id = 0
        self.com_m = np.zeros(3)
        self.last_update_ns = 0
        self.last_env_time_s = math.nan
        self.env_rate_hz = 0.0
        self._env_arrivals = np.zeros(ENV_RATE_WINDOW, dtype=np.int64)
        self._env_n = 0
        self.updates = 0
        self.acks = 0
        self.update_errors = 0
        self.engagements = 0
        # lifecycle (changed only by transition())
        self.state = LS["starting"]
        self.watchdog = WD_OK
        self.fault = Fault.NONE
        self.device_fault = 0
        self.faults_total = 0
        self.last_reason = Reason.START
        self._stop_flag = False
        # stalls: a late loop trips the device's own watchdog; it recovers once on time again
        self._dev_wd_ns = int(round(float(getattr(self.device.limits, "watchdog_s", 0.0)) * 1e9))
        self._recover_ns = int(scfg["stall_recover_s"] * 1e9)
        self._stall_window_ns = int(scfg["stall_window_s"] * 1e9)
        self._stall_explains_ns = int(STALL_EXPLAINS_S * 1e9)
        self._speeding = False  # a speed trip while nothing was rendered is logged when it starts
        self._rendered_ever = False  # a session was ever engaged (force rendered, or ramping in)
        self._stall_trips_max = int(scfg["stall_trips_max"])
        self._trip_times: list[int] = []
        #: a gap between two steps' device writes longer than this is a stall: half the device's
        #: own watchdog (a step late by a period or two threatens nothing; it is counted as a
        #: missed deadline, not as being off time)
        self._stall_gap_ns = max(2 * self.period_ns, self._dev_wd_ns // 2 if self._dev_wd_ns > 0 else 25_000_000)
        self.stall_trips = 0
        self.stall_recoveries = 0
        self._stall_ns = 0        # the latest gap between steps longer than two periods
        self._stall_at = 0        # when it ended
        self._ontime_since = 0    # the end of the last stall
        #: the supervisor's pid; when it changes (the supervisor died) the loop stops cleanly
        self.parent_pid = 0
        self.watchdog_ns = int(scfg["watchdog_s"] * 1e9)
        self._use_engine_frame = mcfg["contact_frame"] == "engine"
        self._hk_n = 0
        self._kernels_compiled = -1
        self._kernels: list = []
        self._pending = None  # the newest ContactUpdate received, applied in the next step
        self._ack_due = None  # the ContactUpdate applied in the previous step, acknowledged in this one
        # the two stages, bound once: a bound method made in the step would be an allocation there
        self._ack_stage = self._ack
        self._apply_stage = self._on_update
        self.dropped_at_start = 0  # datagrams that queued before start() (counted, not read)
        self.advice: EngineAdvice | None = None
        self._scratch_pose = np.zeros(13)
        self._no_joints = np.zeros(0)
        # the acknowledgement's arrays: views made once (the ack encodes from them as they are)
        self._ack_pose = self._scratch_pose[:7]
        self._ack_twist = self._scratch_pose[7:13]
        self._ack_wrench = self.ctrl.cs[ctl.CS_HAND:ctl.CS_HAND + 6]
        #: the device's inputs (buttons, gripper) of the newest read: a view of the state row
        self._ack_inputs = self.dev[DS_BUTTONS:DS_BUTTONS + 3]
        self._R = np.zeros((3, 3))
        self._c = np.zeros(3)
        self._st_missed = ST["missed_deadlines"]
        # arrays the kernel gets while no model is engaged (active = 0: never stepped)
        self._dummy = LocalModel(ToolSpec.one_dof(1.0), period_s=self.dt_s, capacity=1, warm=False).kernel_args()
        #: the model's counters the telemetry row reads its live contacts from (none: zeros)
        self._no_cnt = np.zeros_like(self._dummy[5])
        self._cnt = self._no_cnt
        sh = self.shared
        #: the accounting kernel's fixed arguments, gathered once (each lookup in a step costs)
        self._acc = (sh.tel, sh.head, sh.hist_late, sh.hist_step, sh.stat, int(self.period_ns))
        self.ctrl.hold()  # nothing drives a proxy until a session engages
        # the tick's words and arrays (``tick.TickArrays``: bound again when the model changes)
        self.tk = tick.new_words(self.period_ns)
        tk = self.tk
        tk[tick.TK_STALL_GAP_NS] = self._stall_gap_ns
        tk[tick.TK_HK_EVERY] = max(1, int(round(0.01 * settings.rate_hz)))
        tk[tick.TK_WATCHDOG_NS] = self.watchdog_ns
        tk[tick.TK_SIMULATED] = 1 if self.clock.simulated else 0
        tk[tick.TK_SIM_COST_NS] = int(getattr(self.clock, "step_cost_ns", 0))
        fileno = getattr(self.transport, "fileno", None)
        tk[tick.TK_FD] = fileno() if callable(fileno) else -1
        tk[tick.TK_STATE] = int(self.state)
        sim_arrays = getattr(self.device, "tick_arrays", None)
        self._dev_arrays = sim_arrays() if callable(sim_arrays) else _NO_SIM_DEVICE
        self._io = tick.IO_SIM if callable(sim_arrays) else tick.IO_EXTERNAL
        tk[tick.TK_IO] = self._io
        self._bind()
        st = self.shared.status
        st[ST["period_ns"]] = self.period_ns
        st[ST["rate_hz"]] = settings.rate_hz
        st[ST["force_cap_n"]] = self.ctrl.force_cap_n
        st[ST["rate_limit_n_per_step"]] = self.ctrl.force_rate_n_per_step
        st[ST["loop_state"]] = self.state

    def _bind(self) -> None:
        """The tick's arrays: the controller's, the device's, the engaged model's (or the idle
        dummy's), the shared rings'. Runs at construction and when the engaged model changes."""
        c, sh, tk = self.ctrl, self.shared, self.tk
        margs = self._margs if self._margs is not None else self._dummy
        kind, par, st_, C, CI, cnt, wk = margs
        lmeta, lk, lki, lw = self._largs if self._linkage else _NO_LINKAGE
        self._T = tick.TickArrays(c.cp, c.cs, c.cc, c.cmd, c.hand, c.R, c.c, self.dev, *self._dev_arrays,
                                  par, st_, C, CI, cnt, wk, lmeta, lk, lki, lw,
                                  sh.tel, sh.head, sh.hist_late, sh.hist_step, sh.stat, tk)
        tk[tick.TK_ACTIVE] = 0 if self._margs is None else 1
        tk[tick.TK_LINKAGE] = 1 if self._linkage else 0
        tk[tick.TK_KIND] = int(kind)

    @property
    def _last_write_ns(self) -> int:
        """The end of the last tick (its device write and accounting)."""
        return int(self.tk[tick.TK_LAST_WRITE_NS])

    @property
    def _deadline(self) -> int:
        return int(self.tk[tick.TK_DEADLINE_NS])

    @property
    def _t0(self) -> int:
        return int(self.tk[tick.TK_T0_NS])

    @property
    def _hk_every(self) -> int:
        """Ticks between housekeeping."""
        return int(self.tk[tick.TK_HK_EVERY])

    # ---------------------------------------------------------------------------- lifecycle
    @property
    def stopping(self) -> bool:
        return self.state == LS["stopping"] or self.state == LS["stopped"]

    @property
    def stopped(self) -> bool:
        return self.state == LS["stopped"]

    def transition(self, to: str, reason: Reason, detail: float = 0.0) -> None:
        """Change state (``lifecycle.TRANSITIONS``), apply what the new state means for the force
        and the proxy, log it. Runs at events only (engagement, silence, faults), never per step."""
        frm = LOOP_STATES[int(self.state)]
        if to not in TRANSITIONS[frm]:
            raise RuntimeError(f"haptic loop: no transition {frm} -> {to} ({Reason(reason).name})")
        c = self.ctrl
        if to == "engaged":
            c.engage(slide=self._index_mapping)
            self._rendered_ever = True
        else:
            c.hold()
            if self.model is not None:
                self.model.stop()  # held where it is: nothing pushes it while nothing is rendered
        if to == "idle":
            self._drop_model()
        if to == "fading":
            self.watchdog = WD_SILENT if reason == Reason.SILENT else WD_SESSION_ENDED
        elif to != "fault":
            self.watchdog = WD_OK
        self.state = LS[to]
        self.tk[tick.TK_STATE] = int(self.state)
        self.last_reason = Reason(reason)
        sh = self.shared
        sh.log_transition(self.clock.now_ns(), LS[frm], self.state, int(reason), float(detail))
        sh.status[ST["loop_state"]] = self.state

    def _drop_model(self) -> None:
        self.model = None
        self._margs = None
        self._cnt = self._no_cnt
        self._linkage = False
        self._largs = None
        self.session_id = 0
        self._bind()

    # ---------------------------------------------------------------------------- set-up
    def cold_kernels(self) -> list[str]:
        """The kernels :meth:`warm_up` will compile (nothing in numba's cache for them yet);
        a rigid tool's loop never calls the linkage step, so its missing cache is not counted."""
        from .warm import cold

        return [n for n in cold() if self.kind == "linkage" or n != ctl.haptic_step_linkage.py_func.__qualname__]

    def warm_up(self) -> None:
        """Compile/load every kernel this loop calls, with the argument types the loop passes, on
        throw-away arrays, before the first step: nothing may compile once deadlines are armed
        (a compile takes seconds; ``status.late_compiles`` counts any that still happens)."""
        model_warm_up()
        ingest.warm_up()
        egress.warm_up()
        advice_warm_up()
        s = self.settings
        c = ctl.Controller(s, self.device.kind, self.device.limits)
        dev_kind = self.device.kind
        tmp = LocalModel(ToolSpec.planar(1.0, 1e-3) if dev_kind == "planar" else
                         ToolSpec.one_dof(1.0) if dev_kind == "1dof" else ToolSpec.spatial(1.0, (1e-3,) * 3),
                         period_s=self.dt_s, capacity=4, warm=False)
        dev = empty_state()
        for active in (0, 1):
            for drive, slide in ((1.0, 1.0), (0.0, 0.0)):
                c.cs[ctl.CS_DRIVE] = drive
                c.cs[ctl.CS_SLIDE] = slide
                ctl.haptic_step(c.cp, c.cs, c.cc, dev, c.cmd, active, *tmp.kernel_args(), c.hand, c.R, c.c)
        if self.kind == "linkage":
            links = (LinkSpec(0.1, inertia_kg_m2=(1e-4, 1e-4, 1e-4)),
                     LinkSpec(0.1, (0.03, 0.0, 0.0), (1e-4, 1e-4, 1e-4), 0, "revolute", (0.0, 0.0, 1.0), (0.06, 0.0, 0.0)))
            lm = LocalModel(ToolSpec.linkage(links, 1, dev_kind == "planar"), period_s=self.dt_s, capacity=4, warm=False)
            kind_, par_, st_, C_, CI_, cnt_, wk_ = lm.kernel_args()
            for drive in (1.0, 0.0):
                c.cs[ctl.CS_DRIVE] = drive
                ctl.haptic_step_linkage(c.cp, c.cs, c.cc, dev, c.cmd, par_, *lm.linkage_args()[:3], st_, C_, CI_,
                                        cnt_, wk_, lm.linkage_args()[3], c.hand)
        ctl.fade_only(c.cp, c.cs, c.cc, c.cmd)
        c.cut()
        scratch = SharedState.local(4)  # the same views (so the same kernel types) as the shared block's
        account(scratch.tel, scratch.head, scratch.hist_late, scratch.hist_step, scratch.stat, self.period_ns, 1, 1,
                0, self.state, self.updates, c.cs, self._no_cnt, dev, c.cmd)
        record_contacts(scratch.contacts, 0.0, 0.0, 1, 1,  # the decoder's views, as _on_update records them
                        *frozen_copies(np.zeros((4, 3), dtype=np.int64), np.zeros((4, 3)), np.zeros((4, 3)),
                                       np.zeros(4)))
        ctl.proxy_hand_state(tmp.kind, tmp.kernel_args()[1], tmp.kernel_args()[2], c.R, c.c, self._scratch_pose, 0)
        pose = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
        pose.flags.writeable = False  # what the decoder hands out: read-only views of the packet
        joints = np.zeros(2)
        joints.flags.writeable = False
        for qk in ctl.Q_KINDS.values():
            ctl.tool_q_from_pose(qk, pose, np.zeros(3), np.array([1.0, 0.0, 0.0]), joints, np.zeros(9))
            ctl.tool_q_from_pose(qk, pose, np.zeros(3), np.array([1.0, 0.0, 0.0]), self._no_joints, np.zeros(9))
        adv_a, adv_p = EngineAdvice(0.01).kernel_arrays
        for sep in (joints, joints[:0]):  # the update's separation column: read-only, empty or not
            ctl.ack_state(tmp.kind, tmp.kernel_args()[1], tmp.kernel_args()[2], c.R, c.c, self._scratch_pose, adv_a,
                          adv_p, 0.0, pose, sep)
        # the tick and the compiled loop, with this loop's argument types, on throw-away arrays
        tk = tick.new_words(self.period_ns)
        tk[tick.TK_SIMULATED] = 1
        tk[tick.TK_IO] = self._io
        Tw = tick.TickArrays(c.cp, c.cs, c.cc, c.cmd, c.hand, c.R, c.c, dev, *(a.copy() for a in self._dev_arrays),
                             *tmp.kernel_args()[1:], *(a.copy() for a in _NO_LINKAGE), scratch.tel, scratch.head,
                             scratch.hist_late, scratch.hist_step, scratch.stat, tk)
        tick.tick(Tw, 0, 0)
        tk[tick.TK_STOP] = 1
        tick.run_ticks(Tw)
        warm = getattr(self.device, "warm_up", None)
        if callable(warm):
            warm()
        self._kernels = package_kernels()
        self._kernels_compiled = sum(len(d.overloads) for d in self._kernels)

    def start(self) -> None:
        """Drop what queued while the loop was built and warmed, arm the device and set the first
        deadline one period from now."""
        # Datagrams that waited through the warm-up (a cold cache: a minute) are stale: a client
        # retried its Hello since, maybe from another socket, and a session opened for an old one
        # would hold the slot for a peer that is gone (the client would hear SERVER_FULL).
        tr, buf = self.transport, self.rxbuf
        for _ in range(_START_DRAIN_MAX):
            if tr.recv_into(buf)[1] is None:
                break
            self.dropped_at_start += 1
        self.device.enable()
        now = self.clock.now_ns()
        tk = self.tk
        tk[tick.TK_T0_NS] = now
        tk[tick.TK_DEADLINE_NS] = now + self.period_ns
        tk[tick.TK_LAST_WRITE_NS] = now
        self._ontime_since = now
        if self._kernels_compiled < 0:
            self._kernels = package_kernels()
            self._kernels_compiled = sum(len(d.overloads) for d in self._kernels)
        st = self.shared.status
        st[ST["t_start_ns"]] = now
        self.transition("idle", Reason.START)
        st[ST["ready"]] = 1.0

    # ---------------------------------------------------------------------------- the step
    def step(self) -> bool:
        """One haptic step: wait for the deadline, then :meth:`step_at`. Returns ``False`` once
        the loop has stopped."""
        tk = self.tk
        deadline = int(tk[tick.TK_DEADLINE_NS])
        wake = self.clock.wait_until(deadline)
        late = wake - deadline
        period = self.period_ns
        if late >= period:  # missed whole periods: skip them rather than burst
            missed = late // period
            self.shared.status[self._st_missed] += missed
            tk[tick.TK_DEADLINE_NS] = deadline + (missed + 1) * period
            self.ctrl.skip(missed)  # fades and ramp-ins keep their times, not their step counts
        else:
            tk[tick.TK_DEADLINE_NS] = deadline + period
        return self.step_at(wake, late)

    def step_at(self, wake: int, late: int) -> bool:
        """The step woken at ``wake``: the tick first (device read, controller and model, safety
        filter, device write, accounting: ``tick.tick``, one compiled call), then what needs
        Python (faults, the lifecycle, the protocol: an update to acknowledge, one to apply,
        datagrams to read, housekeeping), so the device is sampled and commanded right after the
        deadline whatever the protocol costs. Returns ``False`` once the loop has stopped."""
        clock = self.clock
        tk = self.tk
        gap = wake - int(tk[tick.TK_LAST_WRITE_NS])
        if gap > self._stall_gap_ns:  # the process did not run: a stall (what the device saw, too)
            self._stall_ns = gap
            self._stall_at = wake
            self._ontime_since = wake
            self._quiet_since()
            if gap >= self._dev_wd_ns > 0:
                self._on_own_stall(wake)
        # 1: the tick
        if self._io == tick.IO_EXTERNAL:
            tk[tick.TK_EXT_RC] = self.device.read(self.dev)
            rcs = tick.tick(self._T, wake, late)
            rc_w = self.device.write(self.ctrl.cmd)
            if rc_w:
                rcs |= (rc_w & 0xFF) << 16
            if clock.simulated:
                clock.charge()
            # a driver in Python: its write ends the step (the tick accounted up to its call)
            tk[tick.TK_LAST_WRITE_NS] = clock.now_ns()
        else:
            rcs = tick.tick(self._T, wake, late)
            if clock.simulated:
                clock.charge()
        self._after_tick(rcs, wake)
        # 2: acknowledge the ContactUpdate the previous step applied, then apply the one received
        # before. Applying (the model update) and acknowledging (the engine's advice, the
        # ProxyState's encoding) each cost some us of Python: spread over consecutive steps, no
        # step pays for two of them (nor for housekeeping), unless updates arrive in every step.
        busy = False
        upd = self._ack_due
        if upd is not None:
            self._ack_due = None
            busy = self._survive(self._ack_stage, upd, wake)
        upd = self._pending
        if upd is not None:
            self._pending = None
            busy = self._survive(self._apply_stage, upd, wake)
        elif self.state == LS["engaged"] and wake - max(self.last_update_ns, self._stall_at) > self.watchdog_ns:
            # (the environment's silence is counted from the end of this loop's own last stall:
            # while the loop did not run, the environment's updates waited in the socket)
            self.transition("fading", Reason.SILENT, (wake - self.last_update_ns) * 1e-6)
        if self._poll(wake):
            busy = True
        tk[tick.TK_NEEDS_PYTHON] = 1 if (self._pending is not None or self._ack_due is not None) else 0
        self._maybe_housekeeping(busy)
        return not self.stopped

    def _after_tick(self, rcs: int, wake: int) -> None:
        """What a tick's results ask of the lifecycle: a fault, or a fade that reached zero."""
        if rcs:
            rc, rc_dev, rc_w = rcs & 0xFF, (rcs >> 8) & 0xFF, (rcs >> 16) & 0xFF
            self._on_fault(rc, rc_dev or rc_w, wake)
        elif self._speeding:
            self._speeding = False
        if (self.state == LS["fading"] or self.state == LS["stopping"]) and self.ctrl.cs[ctl.CS_GAIN] <= 0.0:
            self._after_fade()

    def _poll(self, wake: int) -> bool:
        """Read waiting datagrams without blocking (at most ``max_packets_per_step`` and
        ``POLL_BUDGET`` of the period); the newest ContactUpdate wins (applied next step). True
        when one was received."""
        tr = self.transport
        ep = self.endpoint
        buf = self.rxbuf
        got = False
        poll_end = wake + self.poll_budget_ns
        now_ns = self.clock.now_ns
        self.tk[tick.TK_RX_PENDING] = 0
        for _ in range(self.max_packets_per_step):
            n, peer = tr.recv_into(buf)
            if peer is None:
                break
            m = ep.receive(buf[:n], peer, wake)  # bytearray slice: a copy the update may keep
            if m is not None:
                self._pending = m
                got = True
            if now_ns() > poll_end:
                self.poll_cut += 1
                self.tk[tick.TK_RX_PENDING] = 1  # more waits: come back next period
                break
        return got

    def _maybe_housekeeping(self, busy: bool) -> None:
        """Housekeeping every ``TK_HK_EVERY`` ticks, not in a step that received or applied an
        update (each costs some us, as housekeeping does) unless updates arrive in every step (a
        flood): then at most ``_HK_MAX_DEFER`` steps late."""
        tk = self.tk
        tk[tick.TK_HK_COUNT] += 1
        n = int(tk[tick.TK_HK_COUNT])
        every = int(tk[tick.TK_HK_EVERY])
        if n >= every and (not busy or n >= every + _HK_MAX_DEFER):
            tk[tick.TK_HK_COUNT] = 0
            self._housekeeping(self.clock.now_ns())

    def _quiet_since(self) -> None:
        """The environment's silence counts from its last update or this loop's last stall."""
        self.tk[tick.TK_QUIET_SINCE_NS] = max(self.last_update_ns, self._stall_at)

    def _survive(self, handler, upd, now: int) -> bool:
        """``handler(upd, now)``, outlived: the loop must survive anything an update can raise (e.g.
        a finite but absurd proxy state the codec refuses). Treated like a non-finite value (zero
        wrench, device disabled, re-arm needed), never dying with force on. True: the step was busy."""
        try:
            handler(upd, now)
        except Exception:  # noqa: BLE001 - see above
            self.update_errors += 1
            self._on_fault(ctl.RC_NONFINITE, 0, now, Reason.UPDATE_ERROR)
        return True

    def _contacts(self) -> float:
        return float(self._cnt[K_M])  # the model's live contacts (no model: zeros)

    # ---------------------------------------------------------------------------- events
    def _on_update(self, upd, now: int) -> None:
        sid = upd.session_id
        keys = upd.keys
        if sid != self.session_id or self.model is None:
            if self.model is not None and self.session_id in self.endpoint.sessions:
                return  # another session owns the model; its updates are the only ones applied
            if self.model is not None and self.ctrl.cs[ctl.CS_GAIN] > 0.0:
                # the previous session's force is still fading out: engage once it is gone, so
                # the new session ramps in from zero (its updates until then are not acked)
                return
            if self.stopping:
                return
            self._engage(upd, now)
            if self.model is None:
                return  # not engaged (a Hello the model cannot hold)
        else:
            # the decoder's read-only views go to the kernels as they are (no copies: the codec
            # and the session checked them, and warm_up compiled the kernels for these types)
            code = self.model.update_arrays(keys, upd.position_m, upd.normal, upd.separation_m,
                                            upd.v_constr_m_per_s, keys.shape[0], self._engine_q(upd))
            if code != 0:
                self.update_errors += 1
                return
        self._track_env(upd, now)
        self.updates += 1
        self.tk[tick.TK_UPDATES] = self.updates
        record_contacts(self.shared.contacts, (now - self._t0) * 1e-9, float(upd.env_time_s), self.updates,
                        keys.shape[0], keys, upd.position_m, upd.normal, upd.separation_m)
        if self.state == LS["fading"] and self.watchdog == WD_SILENT:
            self.transition("engaged", Reason.RESUMED)
        self._ack_due = upd  # acknowledged in the next step, with the proxy state the update led to

    def _engine_q(self, upd):
        """The engine's tool configuration for the update (None: the paper's eq. 1). A linkage's
        needs the engine's joint positions too (``ContactUpdate.tool_joint_position``); an update
        without them (a v1.0 client) is located with the paper's eq. 1."""
        if not self._use_engine_frame:
            return None
        joints = self._no_joints
        if self._linkage:
            joints = upd.tool_joint_position
            if len(joints) != self._n_joints:
                return None
        ctl.tool_q_from_pose(self._qk, upd.tool_pose, self._hello_com, self._hello_axis, joints, self._tool_q)
        return self._tool_q

    def _granted(self, hello) -> tuple[float, int]:
        """What the handshake grants this Hello (the session layer's rule)."""
        cfg = self.server_config
        return (min(float(hello.epsilon_m), cfg.max_epsilon_m),
                min(int(hello.max_contacts), cfg.max_contacts, self.endpoint.codec.limits.max_contacts))

    def _check_hello(self, hello) -> str:
        """A Hello whose tool the model can hold with this server's contact parameters and rate:
        "" or why not (Reject INVALID_HELLO), so a session never engages a tool that would fail.
        The model built for the check is the one the engagement uses."""
        return self.models.check(hello, *self._granted(hello))

    def _track_env(self, upd, now: int) -> None:
        """The environment's rate over a window of arrivals: the last ``ENV_RATE_WINDOW`` updates
        applied, or those of the last second if fewer (an average of 1/dt would be ruled by
        back-to-back updates that queued while the loop stalled)."""
        self._env_arrivals[self._env_n % ENV_RATE_WINDOW] = now
        self._env_n += 1
        k = min(self._env_n, ENV_RATE_WINDOW)
        oldest = now
        count = 0
        for i in range(1, k + 1):  # newest first, back to the window's start or a second ago
            t = int(self._env_arrivals[(self._env_n - i) % ENV_RATE_WINDOW])
            if now - t > 1_000_000_000:
                break
            oldest = t
            count = i
        self.env_rate_hz = (count - 1) / ((now - oldest) * 1e-9) if count > 1 and now > oldest else 0.0
        self.last_update_ns = now
        self.last_env_time_s = upd.env_time_s
        self._quiet_since()

    def _ack(self, upd, now: int) -> None:
        """The engine's advice (epsilon to use next, the lead; one kernel) and the ProxyState that
        acknowledges ``upd`` (applied in the previous step; ``ack_seq`` its seq, not the newest
        received since). Nothing if its session no longer owns the model (closed, timed out)."""
        m = self.model
        if m is None or upd.session_id != self.session_id:
            return
        state = SERVER_STATE_BY_CODE[int(self.state)]
        adv = self.advice
        if self._linkage:
            # the root frame's pose and twist; the hand wrench as the wrench on the root frame's
            # origin plus one effort per joint (J_h^T F_h split by coordinates)
            js = self._jstate
            m.joint_state_into(self._ack_wrench, js)
            pose, twist, wrench, effort, jq, jqd = js
            advice_update(*adv.kernel_arrays, now * 1e-9, pose, twist, upd.tool_pose, upd.separation_m, False)
            if self.endpoint.send_proxy_state(self.session_id, now, pose, twist, wrench, server_time_s=m.time_s,
                                              joint_position=jq, joint_velocity=jqd, joint_effort=effort,
                                              server_state=state, epsilon_m=adv.epsilon_m, lead_s=adv.lead_s,
                                              ack_seq=upd.seq, trusted=True, inputs=self._ack_inputs):
                self.acks += 1
            return
        mg = self._margs
        ctl.ack_state(mg[0], mg[1], mg[2], self._R, self._c, self._scratch_pose, *adv.kernel_arrays, now * 1e-9,
                      upd.tool_pose, upd.separation_m)
        if self.endpoint.send_proxy_state(self.session_id, now, self._ack_pose, self._ack_twist, self._ack_wrench,
                                          server_time_s=m.time_s, server_state=state, epsilon_m=adv.epsilon_m,
                                          lead_s=adv.lead_s, ack_seq=upd.seq, trusted=True, inputs=self._ack_inputs):
            self.acks += 1

    def _engage(self, upd, now: int) -> None:
        sess = self.endpoint.sessions.get(upd.session_id)
        if sess is None:
            return
        s = self.settings
        mcfg = s["model"]
        hello = sess.hello
        linkage = self.kind == "linkage"
        try:
            tool, model = self.models.take(hello, float(sess.epsilon_m), sess.max_contacts)
        except ValueError:
            self.update_errors += 1  # the handshake's check refuses such a Hello; never engage it
            return
        if linkage:
            self._n_joints = len(tool.links) - 1
            qkind = "linkage-planar" if tool.planar else "linkage-spatial"
            joints = getattr(upd, "tool_joint_position", None)
            if joints is None or len(joints) != self._n_joints:
                joints = np.zeros(self._n_joints)  # a v1.0 client: the chain starts at q = 0
            model.reset(q_from_tool_pose(qkind, upd.tool_pose, None, None, np.asarray(joints, dtype=float)))
        else:
            qkind = tool.kind
            model.reset(q_from_tool_pose(tool.kind, upd.tool_pose, hello.com_m, hello.axis))
        self._linkage = linkage
        self._largs = model.linkage_args() if linkage else None
        if linkage:  # the acknowledgement's arrays (``_ack``), written in place at every update
            nj = len(tool.links) - 1
            self._jstate = (np.zeros(7), np.zeros(6), np.zeros(6), np.zeros(nj), np.zeros(nj), np.zeros(nj))
        self._hello_com = np.asarray(hello.com_m, dtype=float)
        self._hello_axis = np.asarray(hello.axis, dtype=float)
        self._tool_kind = qkind
        self._qk = ctl.Q_KINDS[qkind]
        self._tool_q = np.zeros(model.nq)  # the engine's tool configuration of each update
        if model.update_arrays(upd.keys, upd.position_m, upd.normal, upd.separation_m, upd.v_constr_m_per_s,
                               upd.keys.shape[0], self._engine_q(upd)) != 0:
            self.update_errors += 1
        self.model = model
        self._margs = model.kernel_args()
        self._cnt = self._margs[5]
        self._bind()
        self.session_id = upd.session_id
        self.com_m = np.asarray(hello.com_m, dtype=float)
        self._tool_axis = tool.axis
        self.advice = self._new_advice(hello, tool, float(sess.epsilon_m))
        self.device.on_engage()  # a simulated hand's script starts with the session
        self._reindex()
        c = self.ctrl
        c.cs[ctl.CS_PREV:ctl.CS_PREV + 6] = c.cmd  # rate limit continues from the last output
        self.engagements += 1
        self.last_update_ns = now
        self.env_rate_hz = 0.0
        self._env_n = 0
        self._quiet_since()
        if self.fault == Fault.NONE:
            self.transition("engaged", Reason.ENGAGE, self.session_id)

    def _new_advice(self, hello, tool, epsilon_m: float) -> EngineAdvice:
        """What the engine is told with every acknowledgement: the epsilon to use next and the
        lead to extrapolate the proxy by (``server/prediction.py``), capped by the granted epsilon."""
        mcfg = self.settings["model"]
        radius = 0.0  # a linkage's reach is not estimated: the prediction then covers its root only
        if not self._linkage:
            ixx, iyy, izz = (float(v) for v in hello.inertia_kg_m2[:3])
            radius = tool_radius_m(float(hello.mass_kg), (izz,) if tool.kind == "planar" else (ixx, iyy, izz))
            radius += float(np.linalg.norm(np.asarray(hello.com_m, dtype=float)))
        cap = 0.0 if mcfg["policy"] == "lm0" else epsilon_m
        return EngineAdvice(cap, tool_radius_m=radius, predict=mcfg["epsilon_prediction"], lead=mcfg["lead"],
                            epsilon_floor_m=min(mcfg["epsilon_floor_m"], cap), lead_max_s=mcfg["lead_max_s"])

    def _reindex(self) -> None:
        """Map the device onto the proxy's hand point (no jump), unless mapping is absolute. At
        engagement; while the force ramps in, the kernel keeps re-indexing (``control._slide``)."""
        if not self._index_mapping or self._margs is None:
            return
        kind, par, st_ = self._margs[0], self._margs[1], self._margs[2]
        if self._linkage:
            self._scratch_pose[:] = self.model.hand_state()  # the held link's frame
        else:
            ctl.proxy_hand_state(kind, par, st_, self._R, self._c, self._scratch_pose, 0)
        self.device.read(self.dev)
        dev_axis = self.settings["device"].get("axis", (1.0, 0.0, 0.0))
        R_off, p_off, q_off = ctl.index_offset(self.device.kind if self._linkage else self._tool_kind, self.dev[:7],
                                               self._scratch_pose[:7], tool_axis=self._tool_axis, device_axis=dev_axis)
        self.ctrl.set_offset(R_off, p_off, q_off)

    def _after_fade(self) -> None:
        """Gain reached zero while fading or stopping."""
        if self.state == LS["stopping"]:
            self.endpoint.close_all("server stopping")
            self.transition("stopped", Reason.STOPPED)
            return
        if self.watchdog == WD_SESSION_ENDED:
            self.transition("idle", Reason.FADED)

    def _stalled_recently(self, now: int) -> bool:
        """The loop stalled long enough (and recently enough) to explain the device's watchdog.
        A stall inside this step (between its wake-up and its device write) shows only now: the
        time since the previous step's end, and it ended just now, not at the step's wake-up (the
        recovery counts its time on time from here)."""
        t = self.clock.now_ns()
        gap = t - int(self.tk[tick.TK_PREV_WRITE_NS])  # one period and one step's compute when on time
        if gap > self._stall_gap_ns:
            self._stall_ns = gap
            self._stall_at = t
            self._ontime_since = t
        wd = self._dev_wd_ns if self._dev_wd_ns > 0 else 50_000_000
        return self._stall_at > 0 and now - self._stall_at <= self._stall_explains_ns and 2 * self._stall_ns >= wd

    def _on_fault(self, rc: int, dev_code: int, now: int, reason: Reason | None = None) -> None:
        # the device's watchdog, or a remote device's link, cut by this loop's own stall
        if ((dev_code == DEV_FAULT_WATCHDOG or dev_code == DEV_FAULT_LINK) and self.state != LS["stopping"]
                and self._stalled_recently(now)):
            self._on_stall_trip(now)
            return
        if self.state == LS["fault"] or self.stopped:
            return
        if rc == ctl.RC_SPEED and not dev_code:
            if self.state == LS["idle"] and self.ctrl.cs[ctl.CS_GAIN] <= 0.0:
                # nothing is rendered: nothing to fade, nothing that could come back by surprise;
                # a client that connects later engages as usual (lifecycle.FAULT_POLICY)
                if not self._speeding:
                    self._speeding = True
                    self.transition("idle", Reason.SPEED_IDLE)
                return
            self.fault = Fault.SPEED  # fade out (the kernel dropped the gain target), device stays on
            why = Reason.SPEED
        elif dev_code:
            self.fault = Fault.DEVICE
            self.device_fault = dev_code
            self.device.disable()
            self.ctrl.cut()
            why = Reason.DEVICE_FAULT
        else:
            self.fault = Fault.NONFINITE
            self.device.disable()
            self.ctrl.cut()
            why = Reason.NONFINITE
        self.faults_total += 1
        if self.state == LS["stopping"]:
            return  # already ramping down; the output is off
        self.transition("fault", reason or why, dev_code)

    def _on_own_stall(self, now: int) -> None:
        """This loop did not run for at least the device's watchdog: a stall trip whether or not
        the device saw it. A device program that was itself not running when the stall ended
        finds the loop's new commands waiting and never trips; the output and the count of
        repeated stalls must not depend on that. A new stall while the last one's recovery
        waits counts too (the device is off then: only the loop can see it). Before anything
        is rendered, only the device's own trip matters (nothing to cut, nothing to count)."""
        st = self.state
        if st == LS["engaged"] or st == LS["fading"] or (st == LS["fault"] and self.fault == Fault.STALL):
            self._on_stall_trip(now, own=True)

    def _on_stall_trip(self, now: int, own: bool = False) -> None:
        """The device's watchdog cut the output because this loop did not run in time (or the
        loop saw its own stall first). Nothing was wrong with the device or the model: once the
        loop has been on time for ``stall_recover_s`` the force ramps back in (housekeeping),
        unless it happens too often. ``own``: the loop saw the stall itself (a new one)."""
        stall_ms = self._stall_ns * 1e-6
        if self.state == LS["fault"]:
            if self.fault == Fault.STALLS_REPEATED or (self.fault == Fault.STALL and not own):
                return  # the device's latched report of a stall already counted
        self.stall_trips += 1
        if self.state == LS["idle"] and self.ctrl.cs[ctl.CS_GAIN] <= 0.0:
            # nothing was being rendered: no force can come back by surprise
            self.device.enable()
            if not self.device.fault:
                self.transition("idle", Reason.STALL_IDLE, stall_ms)
                return
        self.device.disable()
        self.ctrl.cut()
        self._trip_times = [t for t in self._trip_times if now - t <= self._stall_window_ns] + [now]
        self.faults_total += 1
        if len(self._trip_times) > self._stall_trips_max:
            self.fault = Fault.STALLS_REPEATED
            self.transition("fault", Reason.STALLS_REPEATED, len(self._trip_times))
        else:
            self.fault = Fault.STALL
            self.transition("fault", Reason.STALL, stall_ms)

    def _recover_from_stall(self, now: int) -> None:
        on_time = now - self._ontime_since
        if on_time < self._recover_ns:
            return
        self.device.enable()
        if self.device.fault:
            self.device.disable()
            return  # the device still refuses: try again later
        self.fault = Fault.NONE
        self.device_fault = 0
        self.stall_recoveries += 1
        self.ctrl.cut()  # the device rendered nothing while it was off: ramp in from zero
        if self.model is not None and self.session_id in self.endpoint.sessions:
            self.transition("engaged", Reason.RECOVERED, on_time * 1e-9)
        else:
            self.transition("idle", Reason.RECOVERED, on_time * 1e-9)

    def rearm(self) -> bool:
        """Clear a fault: re-enable the device; force ramps back in from zero."""
        if self.state != LS["fault"]:
            return False
        self.device.enable()
        if self.device.fault:
            return False
        self.fault = Fault.NONE
        self.device_fault = 0
        self._trip_times = []
        self.ctrl.cut()
        if self.model is not None and self.session_id in self.endpoint.sessions:
            self.transition("engaged", Reason.REARM)
        else:
            self.transition("idle", Reason.REARM)
        return True

    def request_stop(self) -> None:
        """Ramp forces down, then send Bye and stop (the next steps do it)."""
        if self.stopping:
            return
        self.transition("stopping", Reason.STOP)
        if self.ctrl.cs[ctl.CS_GAIN] <= 0.0:
            self._after_fade()

    # ---------------------------------------------------------------------------- housekeeping
    def _housekeeping(self, now: int) -> None:
        ep = self.endpoint
        ep.poll(now)
        if self.state == LS["fault"]:
            if self.fault == Fault.STALL:
                self._recover_from_stall(now)
            elif self.fault == Fault.DEVICE and self.device_fault == DEV_FAULT_LINK and not self._rendered_ever:
                # a remote device not connected yet at start-up: no force has ever been rendered,
                # so arming it when its link comes up is not a force "coming back by itself"
                self.device.enable()
                if not self.device.fault:
                    self.fault = Fault.NONE
                    self.device_fault = 0
                    self.transition("idle", Reason.LINK_UP)
        if (self.session_id and self.session_id not in ep.sessions and self.watchdog != WD_SESSION_ENDED
                and (self.state == LS["engaged"] or self.state == LS["fading"])):
            self.transition("fading", Reason.SESSION_ENDED, self.session_id)
        sh = self.shared
        ctrl_ = sh.control
        if self.parent_pid and os.getppid() != self.parent_pid:
            self._stop_flag = True
        if ctrl_[CT["stop"]] != ctrl_[CT["stop_ack"]] or self._stop_flag:
            ctrl_[CT["stop_ack"]] = ctrl_[CT["stop"]]
            self.request_stop()
        if ctrl_[CT["rearm"]] != ctrl_[CT["rearm_ack"]]:
            ctrl_[CT["rearm_ack"]] = ctrl_[CT["rearm"]]
            self.rearm()
        if ctrl_[CT["reset_stats"]] != ctrl_[CT["reset_ack"]]:
            ctrl_[CT["reset_ack"]] = ctrl_[CT["reset_stats"]]
            sh.hist_late[:] = 0
            sh.hist_step[:] = 0
            sh.status[ST["lateness_max_us"]] = 0.0
            sh.status[ST["compute_max_us"]] = 0.0
            sh.status[ST["overruns"]] = 0.0
            sh.status[ST["missed_deadlines"]] = 0.0
        self._hk_n += 1
        if self._hk_n % 100 == 0 and self._kernels_compiled >= 0:
            # about once a second: a kernel compiled after warm-up stalls the loop for seconds;
            # counted so a test (and a person reading status) sees that warm-up missed one
            n = 0
            for d in self._kernels:  # the dispatchers found at warm-up: a few us, no module scan
                n += len(d.overloads)
            if n > self._kernels_compiled:
                sh.status[ST["late_compiles"]] += n - self._kernels_compiled
                self._kernels_compiled = n
        self.publish(now)

    def publish(self, now: int) -> None:
        st = self.shared.status
        ec = self.endpoint.counters
        tc = self.transport.counters
        cc = self.ctrl.cc
        st[ST["t_last_ns"]] = now
        st[ST["updates"]] = self.updates
        st[ST["acks_sent"]] = self.acks
        st[ST["stale_or_duplicate"]] = ec.stale + ec.duplicate
        for i, attr in _ENDPOINT_STATUS:
            st[i] = getattr(ec, attr)
        st[ST["dropped_packets"]] = ec.dropped + getattr(tc, "dropped_oversize_recv", 0)
        st[ST["contacts"]] = self._contacts()
        st[ST["session_id"]] = self.session_id
        st[ST["loop_state"]] = self.state
        st[ST["watchdog"]] = self.watchdog
        st[ST["gain"]] = self.ctrl.cs[ctl.CS_GAIN]
        st[ST["fault"]] = self.fault
        st[ST["device_fault"]] = self.device_fault
        m = self.model
        if m is not None:
            mc = m.counters()
            st[ST["model_nonfinite"]] = mc["nonfinite"]
            st[ST["flips_refused"]] = mc["flips_refused"]
            st[ST["rekeyed"]] = mc["rekeyed"]
            st[ST["recovering"]] = mc["recovering"]
            st[ST["recovery_energy_j"]] = m.recovery_energy_j
        else:
            st[ST["model_nonfinite"]] = 0
            st[ST["recovering"]] = 0
        if self.advice is not None:
            st[ST["advised_epsilon_m"]] = self.advice.epsilon_m
            st[ST["advised_lead_s"]] = self.advice.lead_s
        st[ST["saturated"]] = cc[ctl.CC_SATURATED]
        st[ST["rate_limited"]] = cc[ctl.CC_RATE_LIMITED]
        st[ST["speed_trips"]] = cc[ctl.CC_SPEED_TRIPS]
        st[ST["env_silence_ms"]] = (now - self.last_update_ns) * 1e-6 if self.last_update_ns else -1.0
        st[ST["env_rate_hz"]] = self.env_rate_hz
        st[ST["engagements"]] = self.engagements
        st[ST["faults_total"]] = self.faults_total
        st[ST["telemetry_overwritten"]] = max(0, int(self.shared.head[0]) - self.shared.ring_rows)
        st[ST["wrong_version"]] = self.endpoint.codec.counters.unknown_major
        st[ST["dropped_empty"]] = getattr(tc, "dropped_empty", 0)
        st[ST["poll_budget_cuts"]] = self.poll_cut
        st[ST["stall_trips"]] = self.stall_trips
        st[ST["stall_recoveries"]] = self.stall_recoveries
        st[ST["torque_cap_n_m"]] = self.ctrl.torque_cap_n_m

    # ---------------------------------------------------------------------------- running
    def run(self, *, max_steps: int | None = None, duration_s: float | None = None) -> None:
        """Step until stopped (or ``max_steps`` / ``duration_s`` of loop time, then stop cleanly).

        On the monotonic clock the compiled loop (``tick.run_ticks``) owns the clock and ticks by
        itself, handing back only the steps and the aftermath that need Python; on any other
        clock (simulated time, the naive baseline), or with a driver written in Python (read and
        written by Python), each step is :meth:`step`."""
        from .clock import MonotonicClock

        if type(self.clock) is not MonotonicClock or self._io == tick.IO_EXTERNAL:
            # (a driver in Python is read and written by Python every step)
            self._run_steps(max_steps, duration_s)
        else:
            self._run_compiled(max_steps, duration_s)
        self.publish(self.clock.now_ns())

    def _run_steps(self, max_steps, duration_s) -> None:
        end_ns = None if duration_s is None else self.clock.now_ns() + int(duration_s * 1e9)
        n = 0
        step = self.step
        while step():
            n += 1
            if (max_steps is not None and n >= max_steps) or (end_ns is not None and self._deadline >= end_ns):
                if not self.stopping:
                    self.request_stop()
                    # bounded: the fade takes fade_s; then one more step closes the sessions
                    max_steps = None
                    end_ns = None

    def _run_compiled(self, max_steps, duration_s) -> None:
        tk = self.tk
        # the spin never takes more than a quarter of the period: the thread sleeps every period,
        # so SCHED_FIFO never meets the kernel's real-time throttling (95 % of each second)
        tk[tick.TK_SPIN_NS] = min(int(self.clock.spin_ns), self.period_ns // 4)
        self.shared.status[ST["spin_ns"]] = float(tk[tick.TK_SPIN_NS])
        end_ns = None if duration_s is None else self.clock.now_ns() + int(duration_s * 1e9)
        n0 = int(tk[tick.TK_TICKS])
        steps = 0
        T = self._T
        while not self.stopped:
            ev = tick.run_ticks(T)
            T = self._T  # an engagement binds the tick to the new model's arrays
            if ev == tick.EV_STEP:
                self.step_at(int(tk[tick.TK_WAKE_NS]), int(tk[tick.TK_LATE_NS]))
                steps += 1
            elif ev == tick.EV_TICKED:
                self._after_compiled_tick()
            else:
                tk[tick.TK_STOP] = 0
                self._stop_flag = True
                self._housekeeping(self.clock.now_ns())
            n = steps + int(tk[tick.TK_TICKS]) - n0
            if (max_steps is not None and n >= max_steps) or (end_ns is not None and self._deadline >= end_ns):
                if not self.stopping:
                    self.request_stop()
                max_steps = None
                end_ns = None

    def _after_compiled_tick(self) -> None:
        """What a tick run by ``run_ticks`` left for Python: its results, a datagram, housekeeping."""
        tk = self.tk
        wake = int(tk[tick.TK_LAST_WRITE_NS])
        self._after_tick(int(tk[tick.TK_RC]), wake)
        busy = self._poll(wake)
        tk[tick.TK_NEEDS_PYTHON] = 1 if (self._pending is not None or self._ack_due is not None) else 0
        n = int(tk[tick.TK_HK_COUNT])
        every = int(tk[tick.TK_HK_EVERY])
        if n >= every and (not busy or n >= every + _HK_MAX_DEFER):
            tk[tick.TK_HK_COUNT] = 0
            self._housekeeping(self.clock.now_ns())

    def close(self) -> None:
        """Stop output and release what this loop opened."""
        try:
            self.device.disable()
        finally:
            if self._owns_device:
                self.device.close()
            if self._owns_transport:
                self.transport.close()

    # ---------------------------------------------------------------------------- views
    def counters(self) -> dict:
        d = {
            "updates": self.updates, "acks": self.acks, "update_errors": self.update_errors,
            "engagements": self.engagements, "faults_total": self.faults_total,
            "dropped_at_start": self.dropped_at_start,
            "stall_trips": self.stall_trips, "stall_recoveries": self.stall_recoveries,
            "state": self.state_name, "fault": Fault(self.fault).name.lower(),
            "device_fault": DEV_FAULT_NAMES.get(self.device_fault, str(self.device_fault)),
        }
        d.update({f"ctrl_{k}": v for k, v in self.ctrl.counters().items()})
        d.update({f"session_{k}": v for k, v in self.endpoint.counters.as_dict().items()})
        return d

    @property
    def state_name(self) -> str:
        return LOOP_STATES[int(self.state)]

    def device_time_s(self) -> float:
        return float(self.dev[DS_TIME])

def package_kernels() -> list:
    """The numba dispatchers of every imported module of this package."""
    import sys

    from numba.core.registry import CPUDispatcher

    out = []
    for name, mod in list(sys.modules.items()):
        if not name.startswith("hapticproxy.") or mod is None:
            continue
        for obj in vars(mod).values():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == name:
                out.append(obj)
    return out

def kernel_signatures() -> dict[str, int]:
    """Signatures compiled (or loaded) so far, per numba kernel of this package."""
    return {f"{d.py_func.__module__}.{d.py_func.__name__}": len(d.overloads) for d in package_kernels()}

def kernels_compiled() -> int:
    """Signatures compiled (or loaded) so far by every numba kernel of this package."""
    return sum(kernel_signatures().values())

__all__ = ["HapticLoop", "tool_from_hello", "q_from_tool_pose", "kernels_compiled", "DEV_NSTATE"]
