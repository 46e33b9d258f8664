"""The loop's protocol side: the one owner of the sessions, the engaged model and the updates.

``ProtocolSide`` reads the transport (:meth:`poll`: bounded in count and time; the session
layer validates, the newest ContactUpdate is kept) and hands each update to the tick
(:meth:`exchange`): the first of a session engages the model (:meth:`engage`: it builds nothing
new, it takes the model the Hello's check built, re-indexes the device and binds the tick to the
model's arrays); every update is staged in the model's update slot (:meth:`stage`,
``model/slot.py``), which the next tick applies and acknowledges from; the tick's result is
taken and the ProxyState sent (:meth:`take`: the engine's advice, the acknowledgement from the
slot). Staging and taking need no lock: the slot's words say whose its arrays are. It runs in
the Python part of a step after the device was written, or in a thread beside the tick; nothing
here runs per haptic period unless an update arrived.
"""
from __future__ import annotations

import math
import sys

import numpy as np

from ..protocol.codec import Codec
from ..protocol.session import ServerConfig, ServerEndpoint
from ..protocol.vocab import JOINT_TYPE_NAMES, TOOL_KIND_NAMES, TOOL_KINDS_BY_NAME
from . import control as ctl
from . import egress, ingest, tick
from .lifecycle import LS, SERVER_STATE_BY_CODE, Fault, Reason
from .loop_lifecycle import WD_SILENT
from .model.layout import K_M, S_T
from .model.slot import AX_GRANTED_J, AX_HAND, AX_INPUTS, AX_WORK_J
from .model.model import ContactParams, LinkSpec, LocalModel, ToolSpec
from .prediction import EngineAdvice, advice_update, tool_radius_m
from .rings import record_contacts

#: Share of the period the poll may spend reading datagrams before it leaves the rest for the
#: next step. Refusing a datagram usually costs 2-6 us, but a 1 kB msgpack of 1,000 nested
#: arrays costs ~40 us to unpack and refuse: 32 of them per step stretched steps to milliseconds
#: (measured with ``tests/faults``), so the count bound alone does not bound the time.
POLL_BUDGET = 0.25
#: updates over which the environment's rate is measured (``ProtocolSide.track_env``)
ENV_RATE_WINDOW = 32


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

    def tool_of(self, hello):
        """The tool of the model kept for ``hello`` by the last :meth:`check` (None: none kept)."""
        for h, _, built in reversed(self._kept):
            if h is hello:
                return built[0]
        return None

    def take(self, hello, epsilon_m: float, max_contacts: int):
        """The model the check built for this Hello with these grants, or a new one."""
        key = (float(epsilon_m), int(max_contacts))
        for i, (h, k, built) in enumerate(self._kept):
            if h is hello and k == key:
                del self._kept[i]
                return built
        return self.build(hello, epsilon_m, max_contacts)


class ProtocolSide:
    """Sessions, the engaged model, the updates and their acknowledgements of one ``HapticLoop``
    (its ``proto``)."""

    def __init__(self, loop, *, transport, endpoint=None, models=None, hmac_key=None,
                 max_packets_per_step: int = 32) -> None:
        self.loop = loop
        settings = loop.settings
        self.transport = transport
        self.max_packets_per_step = int(max_packets_per_step)
        self.poll_budget_ns = int(POLL_BUDGET * settings.period_ns)
        self.poll_cut = 0  # steps whose poll stopped at the time budget (datagrams left for later)
        self.models = models or ModelFactory(settings, loop.device.kind, loop.dt_s)
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
            supported_tools=frozenset({TOOL_KINDS_BY_NAME[loop.kind]}),
            hello_check=self.check_hello,
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
            transport.send, self.server_config, hmac_key=hmac_key,
            codec=Codec(self.server_config.limits, contact_check=ingest.contacts_surely_valid,
                        proxy_state_packer=(egress.ProxyStatePacker(self.server_config.limits.max_links)
                                            if sys.byteorder == "little" else None)),
            update_check=ingest.update_surely_in_bounds,
            update_parser=ingest.ContactParser(self.server_config.limits) if sys.byteorder == "little" else None)
        self.rxbuf = bytearray(transport.max_packet_bytes)
        #: a linkage tool is engaged: the tick runs ``control.haptic_step_linkage``
        self._linkage = False
        self._largs = None
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
        self.granted_j = 0.0  # energy engines granted the passivity layer (ContactUpdate.work_on_tool_j), J
        self.engagements = 0
        self._use_engine_frame = mcfg["contact_frame"] == "engine"
        self._pending = None  # the newest ContactUpdate received, staged in the next step
        #: the ContactUpdate staged in the model's slot until the tick is done with it
        #: (``TK_UPD_DONE`` reaches ``_stage_seq``); the next is staged after it is taken
        self._staged = None
        self._staged_ns = 0
        self._stage_seq = 0
        #: beside a ticking thread: what :meth:`exchange` left for a pass with the tick's lock (an
        #: engagement, a taken update's transition)
        self.needs_lock = False
        # the stages, bound once: a bound method made in the step would be an allocation there
        self._apply_stage = self.on_update
        self._take_stage = self._take
        self.advice: EngineAdvice | None = None
        self._scratch_pose = np.zeros(13)
        self._no_joints = np.zeros(0)
        # the acknowledgement's arrays: views made once (the ack encodes from them as they are;
        # the hand wrench and the inputs are the slot's, views made at engagement)
        self._ack_pose = self._scratch_pose[:7]
        self._ack_twist = self._scratch_pose[7:13]
        self._ack_wrench = self._ack_inputs = None
        self._R = np.zeros((3, 3))
        self._c = np.zeros(3)
        # arrays the tick gets while no model is engaged (active = 0: never stepped)
        self.dummy = LocalModel(ToolSpec.one_dof(1.0), period_s=loop.dt_s, capacity=1, warm=False).kernel_args()
        #: the model's counters the telemetry row reads its live contacts from (none: zeros)
        self.no_cnt = np.zeros_like(self.dummy[5])
        self._cnt = self.no_cnt

    def kernel_args(self):
        """``(kind, par, st, C, CI, cnt, wk)`` of the engaged model, or the idle dummy's."""
        return self._margs if self._margs is not None else self.dummy

    def linkage_args(self):
        return self._largs if self._linkage else None

    def session_live(self) -> bool:
        """A session owns the engaged model (force may come back to it after a fault)."""
        return self.model is not None and self.session_id in self.endpoint.sessions

    def contacts(self) -> float:
        return float(self._cnt[K_M])  # the model's live contacts (no model: zeros)

    def quiet_since(self) -> None:
        """The environment's silence counts from its last update or the loop's last stall."""
        lp = self.loop
        lp.tk[tick.TK_QUIET_SINCE_NS] = max(self.last_update_ns, lp.life.stall_at)

    def drop_model(self) -> None:
        self._unstage()
        self.model = None
        self._margs = None
        self._cnt = self.no_cnt
        self._linkage = False
        self._largs = None
        self.session_id = 0
        self.loop.bind()

    # ------------------------------------------------------------------ the update's way
    def exchange(self, now: int, locked: bool = True) -> bool:
        """The updates' hand-over with the tick: take its result for the staged one (and send its
        acknowledgement), then stage the newest received. ``locked``: the caller may change what
        the tick uses (no tick runs meanwhile: the single-thread loop, or the tick's lock held);
        else what needs it (an engagement, a transition a taken update brings) is left, and
        ``needs_lock`` says so. True: something was done (the step was busy)."""
        busy = False
        self.needs_lock = False
        if self._staged is not None:
            if int(self.loop.tk[tick.TK_UPD_DONE]) != self._stage_seq:
                return False  # the tick has not applied it yet; the next is staged after it
            if not locked and self._take_needs_lock():
                self.needs_lock = True
                return False
            upd = self._staged
            self._staged = None
            self.survive(self._take_stage, upd, now)
            busy = True
        upd = self._pending
        if upd is not None:
            if upd.session_id == self.session_id and self.model is not None:
                self._pending = None
                busy = self.survive(self._apply_stage, upd, now)  # (on_update: staged, no lock)
            elif locked:
                self._pending = None
                busy = self.survive(self._apply_stage, upd, now)
            else:
                self.needs_lock = True
        return busy

    def _take_needs_lock(self) -> bool:
        """Taking an update changes what the tick uses only when it resumes a fade the silence
        started (a transition), or when the tick started one that Python has not made a
        transition yet (``LoopLife.take_tick_fade`` first)."""
        life = self.loop.life
        return ((life.state == LS["fading"] and life.watchdog == WD_SILENT)
                or int(self.loop.tk[tick.TK_STATE]) != int(life.state))

    def on_update(self, upd, now: int) -> None:
        """An update: the owner's is staged (no lock needed); another session's engages the model
        if it may (with the lock: ``exchange`` calls it so), then is staged; or it is dropped."""
        lp = self.loop
        if self.model is not None and upd.session_id != self.session_id:
            if self.session_id in self.endpoint.sessions:
                return  # another session owns the model; its updates are the only ones applied
            if lp.ctrl.cs[ctl.CS_GAIN] > 0.0:
                # the previous session's force is still fading out: engage once it is gone, so
                # the new session ramps in from zero (its updates until then are not acked)
                return
        if self.model is None or upd.session_id != self.session_id:
            if lp.life.stopping:
                return
            self.engage(upd, now)
            if self.model is None:
                return  # not engaged (a Hello the model cannot hold)
            self.stage(upd, now, engaging=True)
            return
        self.stage(upd, now)

    def stage(self, upd, now: int, engaging: bool = False) -> None:
        """``upd`` (decoded and checked: its arrays go as they are) into the engaged model's slot,
        then published to the tick (``TK_UPD_SEQ``). Only while the slot is Python's (nothing
        staged, or the tick done with it and taken). ``engaging``: the session's first update,
        whose declared work is not granted (it is work since a previous update: there is none)."""
        tk = self.loop.tk
        U = self.model.slot
        n = upd.keys.shape[0]
        U.keys[:n] = upd.keys
        U.pos[:n] = upd.position_m
        U.nrm[:n] = upd.normal
        U.sep[:n] = upd.separation_m
        U.vc[:n] = upd.v_constr_m_per_s
        q = self.engine_q(upd)
        if q is not None:
            U.q[:] = q
        U.ax[AX_WORK_J] = 0.0 if engaging else max(0.0, float(upd.work_on_tool_j))
        tk[tick.TK_UPD_N] = n
        tk[tick.TK_UPD_USE_Q] = 0 if q is None else 1
        tk[tick.TK_UPD_HEARD_NS] = now
        self._staged = upd
        self._staged_ns = now
        self._stage_seq += 1
        tk[tick.TK_UPD_SEQ] = self._stage_seq  # last: the arrays above are the tick's from here

    def _unstage(self) -> None:
        """Forget a staged update the tick has not applied (the model goes, or a new one binds):
        called with no tick running."""
        tk = self.loop.tk
        self._staged = None
        tk[tick.TK_UPD_DONE] = tk[tick.TK_UPD_SEQ] = self._stage_seq

    def _take(self, upd, now: int) -> None:
        """The tick applied the staged ``upd`` (``TK_UPD_CODE``) and left what acknowledges it in
        the slot: the books, the transition it brings, the acknowledgement."""
        lp = self.loop
        if int(lp.tk[tick.TK_UPD_CODE]) != 0:
            self.update_errors += 1  # refused by the model's kernel: nothing changed, no ack
            return
        self.granted_j += float(self.model.slot.ax[AX_GRANTED_J])
        self.updates = int(lp.tk[tick.TK_UPDATES])
        if lp.life.state == LS["fading"] and lp.life.watchdog == WD_SILENT:
            lp.life.transition("engaged", Reason.RESUMED)
        self.books(upd, self._staged_ns)  # (heard when received: the silence counts from there, as the tick's)
        self.ack(upd, now)

    def books(self, upd, now: int) -> None:
        """What an applied update leaves for the record, nothing the tick reads: the environment's
        rate, the contact ring's row."""
        lp = self.loop
        self.track_env(upd, now)
        keys = upd.keys
        record_contacts(lp.shared.contacts, (now - lp.t0_ns) * 1e-9, float(upd.env_time_s), self.updates,
                        keys.shape[0], keys, upd.position_m, upd.normal, upd.separation_m)

    def engine_q(self, upd):
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

    def granted(self, hello) -> tuple[float, int]:
        """What the handshake grants this Hello (the session layer's rule)."""
        cfg = self.server_config
        return (min(float(hello.epsilon_m), cfg.max_epsilon_m),
                min(int(hello.max_contacts), cfg.max_contacts, self.endpoint.codec.limits.max_contacts))

    def check_hello(self, hello) -> str:
        """A Hello whose tool the model can hold with this server's contact parameters and rate,
        and the controller can bring to rest on its contacts with the damping the device renders
        (``Controller.hello_refusal``): "" or why not (Reject INVALID_HELLO), so a session never
        engages a tool that would fail. The model built for the check is the one the engagement
        uses."""
        why = self.models.check(hello, *self.granted(hello))
        if why:
            return why
        return self.loop.ctrl.hello_refusal(self.models.tool_of(hello))

    def track_env(self, upd, now: int) -> None:
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
        self.quiet_since()

    def ack(self, upd, now: int) -> None:
        """The engine's advice (epsilon to use next, the lead; one kernel) and the ProxyState that
        acknowledges ``upd``, from the state the tick that applied it left in the slot (``ack_seq``
        its seq, not the newest received since). Nothing if its session no longer owns the model
        (closed, timed out)."""
        m = self.model
        if m is None or upd.session_id != self.session_id:
            return
        U = m.slot
        state = SERVER_STATE_BY_CODE[int(self.loop.life.state)]
        adv = self.advice
        time_s = float(U.ack_st[S_T])
        if self._linkage:
            # the root frame's pose and twist; the hand wrench as the wrench on the root frame's
            # origin plus one effort per joint (J_h^T F_h split by coordinates)
            js = self._jstate
            m.joint_state_into(self._ack_wrench, js, U.ack_st, U.ack_lw)
            pose, twist, wrench, effort, jq, jqd = js
            advice_update(*adv.kernel_arrays, now * 1e-9, pose, twist, upd.tool_pose, upd.separation_m, False)
            if self.endpoint.send_proxy_state(self.session_id, now, pose, twist, wrench, server_time_s=time_s,
                                              joint_position=jq, joint_velocity=jqd, joint_effort=effort,
                                              server_state=state, epsilon_m=adv.epsilon_m, lead_s=adv.lead_s,
                                              ack_seq=upd.seq, trusted=True, inputs=self._ack_inputs):
                self.acks += 1
            return
        mg = self._margs
        ctl.ack_state(mg[0], mg[1], U.ack_st, self._R, self._c, self._scratch_pose, *adv.kernel_arrays, now * 1e-9,
                      upd.tool_pose, upd.separation_m)
        if self.endpoint.send_proxy_state(self.session_id, now, self._ack_pose, self._ack_twist, self._ack_wrench,
                                          server_time_s=time_s, server_state=state,
                                          epsilon_m=adv.epsilon_m, lead_s=adv.lead_s, ack_seq=upd.seq, trusted=True,
                                          inputs=self._ack_inputs):
            self.acks += 1

    def engage(self, upd, now: int) -> None:
        lp = self.loop
        sess = self.endpoint.sessions.get(upd.session_id)
        if sess is None:
            return
        s = lp.settings
        mcfg = s["model"]
        hello = sess.hello
        linkage = lp.kind == "linkage"
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
        # (nothing is staged here: ``exchange`` hands an update on only once the slot is Python's)
        self._ack_wrench = model.slot.ax[AX_HAND:AX_HAND + 6]
        self._ack_inputs = model.slot.ax[AX_INPUTS:AX_INPUTS + 3]
        self.model = model
        self._margs = model.kernel_args()
        self._cnt = self._margs[5]
        lp.bind()
        self.session_id = upd.session_id
        self.com_m = np.asarray(hello.com_m, dtype=float)
        self._tool_axis = tool.axis
        self.advice = self.new_advice(hello, tool, float(sess.epsilon_m))
        lp.device.on_engage()  # a simulated hand's script starts with the session
        self.reindex()
        c = lp.ctrl
        c.cs[ctl.CS_PREV:ctl.CS_PREV + 6] = c.cmd  # rate limit continues from the last output
        self.engagements += 1
        lp.shared.publish_tool(self.engagements, hello.tool_kind, hello.mass_kg, hello.com_m, hello.inertia_kg_m2)
        self.last_update_ns = now
        self.env_rate_hz = 0.0
        self._env_n = 0
        self.quiet_since()
        if lp.life.fault == Fault.NONE:
            lp.life.transition("engaged", Reason.ENGAGE, self.session_id)

    def new_advice(self, hello, tool, epsilon_m: float) -> EngineAdvice:
        """What the engine is told with every acknowledgement: the epsilon to use next and the
        lead to extrapolate the proxy by (``server/prediction.py``), capped by the granted epsilon."""
        lp = self.loop
        mcfg = lp.settings["model"]
        radius = 0.0  # a linkage's reach is not estimated: the prediction then covers its root only
        if not self._linkage:
            ixx, iyy, izz = (float(v) for v in hello.inertia_kg_m2[:3])
            radius = tool_radius_m(float(hello.mass_kg), (izz,) if tool.kind == "planar" else (ixx, iyy, izz))
            radius += float(np.linalg.norm(np.asarray(hello.com_m, dtype=float)))
        cap = 0.0 if mcfg["policy"] == "lm0" else epsilon_m
        return EngineAdvice(cap, tool_radius_m=radius, predict=mcfg["epsilon_prediction"], lead=mcfg["lead"],
                            epsilon_floor_m=min(mcfg["epsilon_floor_m"], cap), lead_max_s=mcfg["lead_max_s"])

    def reindex(self) -> None:
        """Map the device onto the proxy's hand point (no jump), unless mapping is absolute. At
        engagement; while the force ramps in, the kernel keeps re-indexing (``control._slide``)."""
        lp = self.loop
        if not lp.index_mapping or self._margs is None:
            return
        kind, par, st_ = self._margs[0], self._margs[1], self._margs[2]
        if self._linkage:
            self._scratch_pose[:] = self.model.hand_state()  # the held link's frame
        else:
            ctl.proxy_hand_state(kind, par, st_, self._R, self._c, self._scratch_pose, 0)
        lp.device.read(lp.dev)
        dev_axis = lp.settings["device"].get("axis", (1.0, 0.0, 0.0))
        R_off, p_off, q_off = ctl.index_offset(lp.device.kind if self._linkage else self._tool_kind, lp.dev[:7],
                                               self._scratch_pose[:7], tool_axis=self._tool_axis, device_axis=dev_axis)
        lp.ctrl.set_offset(R_off, p_off, q_off)

    def poll(self, wake: int) -> bool:
        """Read waiting datagrams without blocking (at most ``max_packets_per_step`` and
        ``POLL_BUDGET`` of the period); the newest ContactUpdate wins (staged next step). True
        when one was received."""
        lp = self.loop
        tr = self.transport
        ep = self.endpoint
        buf = self.rxbuf
        got = False
        poll_end = wake + self.poll_budget_ns
        now_ns = lp.clock.now_ns
        lp.tk[tick.TK_RX_PENDING] = 0
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
                lp.tk[tick.TK_RX_PENDING] = 1  # more waits: come back next period
                break
        return got

    def survive(self, handler, upd, now: int) -> bool:
        """``handler(upd, now)``, outlived: the loop must survive anything an update can raise (e.g.
        a finite but absurd proxy state the codec refuses). Treated like a non-finite value (zero
        wrench, device disabled, re-arm needed), never dying with force on. True: the step was busy."""
        lp = self.loop
        try:
            handler(upd, now)
        except Exception:  # noqa: BLE001 - see above
            self.update_errors += 1
            lp.life.on_fault(ctl.RC_NONFINITE, 0, now, Reason.UPDATE_ERROR)
        return True
