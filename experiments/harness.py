"""The experiment harness: one description of a run, two ways to run it, one trace.

A :class:`RunSpec` says everything a run needs: the method (controller, update policy,
epsilon, contact frame), the contact parameters, the haptic rate and contact cap, the
environment (engine, scene, rate, extra delay) and the scripted hand on the simulated device
(planar; or 1-DOF for the paper's 1-DOF peg). It runs

- **in real time** (:func:`run_realtime`): the real server (``Supervisor``: the loop alone in its
  own process at the requested rate, the simulated device in that process) and the
  environment client (``ClientRunner`` in a thread of this process) over UDP on 127.0.0.1
  (through an impairing relay that delays it when ``env_delay_s`` > 0); the
  figures come from the telemetry ring in shared memory. This is the issue's "real server loop
  ... the environment over the real protocol at 30-60 Hz".
- **in simulated time** (:func:`run_simulated`): the same ``HapticLoop``, device, controller,
  model and protocol stack in this process on a ``SimClock`` over the ``mem://`` transport,
  with the engine stepped by :class:`SimEnvClient` on its own (variable) schedule in simulated
  time between haptic steps. Deterministic for a given seed, and far cheaper: the trade-off
  sweep and the tests use it. The CPU time of every haptic step is measured for real
  (``perf_counter_ns`` around ``HapticLoop.step``, which never waits on a ``SimClock``).

Both return a :class:`Trace` (device and proxy poses, commanded and environment wrenches,
contacts, updates, per step; the time axis starts when the client engaged the server).

Frames: the world frame of ``clients/scenes.py`` (+y towards the bottom wall, no gravity). The
device is mapped onto the proxy at engagement (``mapping = "index"``), so device poses are in
world coordinates; the hand point is the tool frame's origin = the peg's COM.
"""
from __future__ import annotations

import itertools
import math
import socket
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..clients.geometry import advance_pose  # noqa: F401 - used below and by experiments

#: The three ways of coupling the device to the environment the paper compares (section V).
#: IR: Berkelman's intermediate representation = direct coupling, no proxy deformation (eq. 1
#: at every update), no prediction. LM0: the local model (four-channel controller, proxy
#: deformation) with active geometry. LM5: the same with epsilon-active geometry, 5 mm.
#: The paper's methods. The IR is the paper's baseline and runs on the paper's server: without the
#: passivity layer, which would stop the runaway the figures show it for (Fig. 6:
#: ``rigid_with_layer``); LM0 / LM5 run with the server's defaults.
METHODS: dict[str, dict] = {
    "IR": {"controller": "direct", "policy": "rigid", "epsilon_m": 0.0, "passivity": (("enabled", False),)},
    "LM0": {"controller": "four_channel", "policy": "lm0", "epsilon_m": 0.0},
    "LM5": {"controller": "four_channel", "policy": "deformation", "epsilon_m": 0.005},
}

#: ``RunSpec.recovery`` that turns the deformation recovery off (the paper's model)
RECOVERY_OFF = (("speed_m_per_s", 0.0),)

_NS = 1_000_000_000
_mem_names = itertools.count(1)
TEL_UPDATES = 6  # shm.TEL["updates"]


class RunFailed(RuntimeError):
    """A run that produced no trace; ``loop_exception`` is what the server loop raised."""

    def __init__(self, message: str, loop_exception: str = "") -> None:
        super().__init__(message)
        self.loop_exception = loop_exception


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass(frozen=True)
class Hand:
    """The scripted hand on the device: ``kind`` "constant" (``wrench``) or "sinusoid"
    (``wrench`` is the amplitude per component, ``frequency_hz``), acting from ``start_s`` of
    device time on (zero before: the session engages and the force ramps in first)."""

    kind: str
    wrench: tuple[float, float, float]
    frequency_hz: float = 0.0
    start_s: float = 0.5

    def value(self, t_s: np.ndarray) -> np.ndarray:
        """(n, 3) wrench at device times ``t_s``."""
        t = np.asarray(t_s, dtype=float)
        w = np.asarray(self.wrench, dtype=float)
        on = (t >= self.start_s)[:, None]
        if self.kind == "constant":
            return np.where(on, w[None, :], 0.0)
        s = np.sin(2 * math.pi * self.frequency_hz * (t - self.start_s))
        return np.where(on, s[:, None] * w[None, :], 0.0)

    def device_config(self, seconds: float, folder: Path, device_kind: str = "planar") -> dict:
        """The ``[device.hand]`` table: a ``steps`` profile for a constant wrench, a ``replay``
        of a sampled wrench file (1 kHz, linearly interpolated) for a sinusoid. Wrenches in the
        device's reduced coordinates: planar ``(fx, fy, tz)``; a ``1dof`` device along world x
        takes ``fx`` alone."""
        cols = {"planar": 3, "1dof": 1, "spatial": 6}.get(device_kind)
        if cols is None:
            raise ValueError(f"device_kind: expected planar, 1dof or spatial, got {device_kind!r}")
        # the experiments time the hand from the server's start (start_s is in that time base)
        if self.kind == "constant":
            return {"type": "steps", "start": "server",
                    "steps": [[0.0, [0.0] * cols], [float(self.start_s), list(self.wrench)[:cols]]]}
        if self.kind != "sinusoid":
            raise ValueError(f"hand.kind: expected constant or sinusoid, got {self.kind!r}")
        t = np.arange(0.0, self.start_s + seconds + 1.0, 1e-3)
        path = Path(folder) / f"hand-{abs(hash(self)) & 0xFFFFFFFF:08x}.npz"
        np.savez(path, t_s=t, wrench=self.value(t)[:, :cols])
        return {"type": "replay", "mode": "wrench", "file": str(path), "start": "server"}


@dataclass(frozen=True)
class RunSpec:
    """Everything one run needs (defaults: the paper's static-contact set-up, LM5)."""

    method: str = "LM5"
    controller: str = "four_channel"
    policy: str = "deformation"
    epsilon_m: float = 0.005
    contact_frame: str = "proxy"
    rate_hz: float = 512.0
    stiffness_n_per_m: float = 4000.0
    damping_n_s_per_m: float = 30.0
    restitution: float = 0.0
    capacity: int = 16
    engine: str = "stub"                      # stub | pymunk | peg1d | pybullet
    scene: str = "testbed"
    env_rate_hz: tuple[float, float] = (30.0, 60.0)   # stub: the range its rate wanders in; pymunk, peg1d: [0] fixed
    #: extra one-way delay of every client -> server datagram (the ContactUpdates): in real time an
    #: impairing UDP relay between client and server, in simulated time a delayed queue
    env_delay_s: float = 0.0
    seed: int = 1
    hand: Hand = Hand("constant", (0.0, 0.5, 0.0))
    seconds: float = 5.0                      # after the hand starts
    workspace_m: float = 0.25
    device: tuple = ()                        # extra [device] keys as (key, value) pairs
    device_kind: str = "planar"               # planar | 1dof (along world x) | spatial
    safety: tuple = ()                        # extra [safety] keys as (key, value) pairs
    passivity: tuple = ()                     # [passivity] keys as (key, value) pairs (the server's defaults else)
    #: simulated time only: the engine misreports its contacts the way real engines do, from
    #: ``misreport_from_s`` of engine time on (see :class:`Misreport`): "" (never), "flip" (the
    #: first contact's normal reversed in every ``misreport_every``-th update), "flip-hold" (reversed
    #: in every update), "rekey" (every key renumbered in every ``misreport_every``-th update)
    misreport: str = ""
    misreport_from_s: float = 0.0
    misreport_every: int = 4
    #: deformation recovery of the local model (``LocalModel.set_recovery`` keywords as (key,
    #: value) pairs; () = the model's defaults; ``RECOVERY_OFF`` = the paper's eq. 5 for ever).
    #: Simulated time only: set on the model the loop builds for the session (the real-time
    #: server process takes the [model] config's settings)
    recovery: tuple = ()
    #: simulated time only: every ProxyState reaches the engine this much later (the engine's
    #: tool lags the proxy by that much more than its own tracking and the update period)
    tool_lag_s: float = 0.0
    #: simulated time only: the server's advice to the engine (``server/prediction.py``), as the
    #: ProxyState would carry it: ``predict_epsilon`` the epsilon to use next (bounded by the
    #: granted one), ``lead`` the time the engine extrapolates the proxy's pose by; the engine
    #: here follows both
    predict_epsilon: bool = False
    lead: bool = False
    #: reproduction only (never a server setting): "paper-literal" reads the paper's eq. 6
    #: literally (``LocalModel.read_eq6_literally``: the epsilon-inflated tool rendered, new
    #: contacts by eq. 6); "" the notes' reading (the server's)
    reading: str = ""

    @classmethod
    def for_method(cls, method: str, **kw) -> "RunSpec":
        return cls(method=method, **{**METHODS[method], **kw})

    def but(self, **kw) -> "RunSpec":
        return replace(self, **kw)

    def settings_dict(self, url: str, status_port: int | None, folder: Path) -> dict:
        nd = 2 if self.device_kind == "planar" else 3
        dev = {"driver": "sim", "kind": self.device_kind, "workspace_min_m": [-self.workspace_m] * nd,
               "workspace_max_m": [self.workspace_m] * nd,
               "hand": self.hand.device_config(self.seconds, folder, self.device_kind)}
        if self.scene == "hole":
            # the paper's user turned the handle with the peg: the device starts at 90 deg, so
            # its frame is the world's (the hand's F_x shakes the peg across the hole)
            dev.update({"initial_pose": [0.0, 0.0, math.pi / 2], "rotation_limit_rad": math.pi / 2 + 1.0})
        dev.update(dict(self.device))
        return {
            "loop": {"rate_hz": float(self.rate_hz)},
            "transport": {"url": url},
            "status": {"address": f"127.0.0.1:{status_port or free_port()}"},
            "model": {"policy": self.policy, "epsilon_m": float(self.epsilon_m), "capacity": int(self.capacity),
                      "stiffness_n_per_m": float(self.stiffness_n_per_m),
                      "damping_n_s_per_m": float(self.damping_n_s_per_m), "restitution": float(self.restitution),
                      "contact_frame": self.contact_frame},
            "controller": {"type": self.controller},
            "device": dev,
            # the experiments sweep into the unstable region on purpose (the stable-region sweep,
            # the IR baselines, Fig. 17's stiff hole), at the force-rate limit they were measured with
            "safety": {"allow_outside_stable_region": True, "force_rate_n_per_s": 1000.0, **dict(self.safety)},
            "telemetry": {"ring_s": float(self.hand.start_s + self.seconds + 3.0)},
            "passivity": dict(self.passivity),
        }

    def make_engine(self):
        if self.engine == "stub":
            from ..clients.stub_engine import StubEngine

            return StubEngine(seed=self.seed, rate_range_hz=tuple(self.env_rate_hz))
        if self.engine == "pymunk":
            from ..clients.pymunk_engine import PymunkEngine

            return PymunkEngine(rate_hz=float(self.env_rate_hz[0]))
        if self.engine == "peg1d":
            from ..clients.peg_engine import PegEngine

            return PegEngine(rate_hz=float(self.env_rate_hz[0]))
        if self.engine == "pybullet":
            from ..clients.pybullet_engine import PybulletEngine

            return PybulletEngine(rate_hz=float(self.env_rate_hz[0]))
        raise ValueError(f"engine: expected stub, pymunk, peg1d or pybullet, got {self.engine!r}")


@dataclass
class Trace:
    """What a run produced, per haptic step from the engagement on (world frame, SI units)."""

    spec: RunSpec
    mode: str                      # "realtime" | "simulated"
    t_s: np.ndarray                # since the engagement
    hand_start_s: float            # the hand starts here (same time axis)
    dev: np.ndarray                # (n, 3) device x, y [m], theta [rad]
    proxy: np.ndarray              # (n, 3) proxy hand point x, y, theta
    dev_vel: np.ndarray            # (n, 3) device vx, vy [m/s], w [rad/s]
    cmd: np.ndarray                # (n, 3) wrench written to the device fx, fy [N], tz [N m]
    env: np.ndarray                # (n, 3) environment wrench at the hand point (model output)
    contacts: np.ndarray           # (n,) local contacts in the model
    updates: np.ndarray            # (n,) model updates applied so far
    state: np.ndarray              # (n,) loop state (shm.LS)
    rate_hz: float
    achieved_rate_hz: float
    env_rate_hz: float
    faults: int
    model_nonfinite: int
    rate_limited: int
    saturated: int
    dev_xyz: np.ndarray | None = None        # (n, 3) device x, y, z [m] (spatial devices)
    cmd_xyz: np.ndarray | None = None        # (n, 3) force written to the device fx, fy, fz [N]
    step_us: np.ndarray | None = None        # simulated: CPU time of every loop step [us]
    model_numba_us: np.ndarray | None = None  # simulated: sampled model-kernel steps [us]
    model_numpy_us: np.ndarray | None = None  # simulated: the numpy reference on the same states [us]
    penalty: np.ndarray | None = None         # simulated: (n, 3) penalty + friction wrench at the hand
    update_step: np.ndarray | None = None     # simulated: (n,) bool, a model update was applied this step
    recovering: np.ndarray | None = None      # simulated: (n,) contacts whose deformation was being recovered
    recovery_step_n: np.ndarray | None = None  # simulated: (n,) penalty force the recovery added (fixed pose)
    compute_us: dict = field(default_factory=dict)   # realtime: the loop's compute-time percentiles
    lateness_us: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    @property
    def dt_s(self) -> float:
        return 1.0 / self.rate_hz


def _theta(qw: np.ndarray, qz: np.ndarray) -> np.ndarray:
    return 2.0 * np.arctan2(qz, qw)


def trace_from_rows(spec: RunSpec, mode: str, rows: np.ndarray, **kw) -> Trace:
    from ..server.shm import TEL

    if rows.size == 0:
        raise RuntimeError("no telemetry rows: the client never engaged the server")
    eng = np.nonzero(rows[:, TEL["updates"]] > 0)[0]
    if len(eng) < 10:
        raise RuntimeError("the client never engaged the server")
    i0 = int(eng[0])
    rows = rows[i0:]
    t_abs = rows[:, TEL["t_s"]]
    t = t_abs - t_abs[0]

    def cols(*names):
        return np.stack([rows[:, TEL[n]] for n in names], axis=1)

    dev = cols("dev_x", "dev_y")
    dev = np.column_stack([dev, np.unwrap(_theta(rows[:, TEL["dev_qw"]], rows[:, TEL["dev_qz"]]))])
    prx = cols("proxy_x", "proxy_y")
    prx = np.column_stack([prx, np.unwrap(_theta(rows[:, TEL["proxy_qw"]], rows[:, TEL["proxy_qz"]]))])
    # a column the run did not record (``record_penalty=False``) stays None
    extra_cols = {k: (None if v is None else v[i0:]) for k, v in kw.pop("per_step", {}).items()}
    return Trace(spec=spec, mode=mode, t_s=t, hand_start_s=float(spec.hand.start_s - t_abs[0]),
                 dev=dev, proxy=prx, dev_vel=cols("dev_vx", "dev_vy", "dev_wz"),
                 dev_xyz=cols("dev_x", "dev_y", "dev_z"), cmd_xyz=cols("cmd_fx", "cmd_fy", "cmd_fz"),
                 cmd=cols("cmd_fx", "cmd_fy", "cmd_tz"), env=cols("env_fx", "env_fy", "env_tz"),
                 contacts=rows[:, TEL["contacts"]].copy(), updates=rows[:, TEL["updates"]].copy(),
                 state=rows[:, TEL["loop_state"]].copy(), **extra_cols, **kw)


# ------------------------------------------------------------------------------ simulated time
class Misreport:
    """What real engines do to a contact set that the model must survive (issue 13, section 4):
    edge-edge normals without a fixed sign (``flip``: the first contact's normal reversed, its
    point and depth kept, in one update out of ``every``; ``flip-hold``: in every update) and
    feature ids that get renumbered (``rekey``: every key's feature id moved to a new number in
    one update out of ``every``, the geometry unchanged)."""

    KINDS = ("", "flip", "flip-hold", "rekey")

    def __init__(self, kind: str, from_s: float, every: int) -> None:
        if kind not in self.KINDS:
            raise ValueError(f"misreport: expected one of {self.KINDS}, got {kind!r}")
        if int(every) < 1:
            raise ValueError(f"misreport_every: must be >= 1, got {every!r}")
        self.kind, self.from_s, self.every = kind, float(from_s), int(every)
        self.updates = 0
        self.applied = 0
        self._generation = 0

    def apply(self, env_time_s: float, keys: np.ndarray, normal: np.ndarray, n: int) -> None:
        if not self.kind or env_time_s < self.from_s or n == 0:
            return
        self.updates += 1
        if self.kind == "flip-hold" or (self.kind == "flip" and self.updates % self.every == 0):
            normal[0] *= -1.0
            self.applied += 1
        elif self.kind == "rekey" and self.updates % self.every == 0:
            self._generation += 1
            self.applied += 1
        if self.kind == "rekey" and self._generation:
            keys[:n, 2] += 1_000_000 * self._generation


class SimEnvClient:
    """An engine behind the real protocol, stepped in simulated time (one thread, no sockets).

    Each :meth:`service` (called before every haptic step): read every waiting datagram and
    drive the engine's tool towards the newest ProxyState; when the engine's next step is due,
    step it, query its epsilon-active contacts and send a ContactUpdate, ``delay_s`` later (the
    engine's computation and the network; 0: at once). The next step is due the engine's own
    step length later (its variable rate), as for an engine running in real time."""

    def __init__(self, engine, url: str, clock, *, scene: str, epsilon_m: float, max_contacts: int,
                 delay_s: float = 0.0, misreport: Misreport | None = None, tool_lag_s: float = 0.0,
                 advice=None) -> None:
        from ..clients.engine import ContactBuffer
        from ..clients.runner import hello_fields
        from ..protocol.codec import Hello
        from ..protocol.session import ClientEndpoint
        from ..protocol.transport import open_transport

        self.engine = engine
        self.clock = clock
        self.info = engine.load_scene(scene)
        engine.set_epsilon(epsilon_m)
        self.tr = open_transport(url, "client")
        self.hello = Hello(client_nonce=1, **hello_fields(engine, self.info, epsilon_m, max_contacts))
        self.ep = ClientEndpoint(self.tr.send, self.hello)
        self.buf = ContactBuffer(max_contacts)
        self.pose = np.zeros(7)
        self.delay_ns = int(round(delay_s * _NS))
        self.misreport = misreport or Misreport("", 0.0, 1)
        self.lag_ns = int(round(tool_lag_s * _NS))
        self.inbox: list = []      # ProxyStates on their way to the engine (tool_lag_s)
        #: the server's EngineAdvice (None: a plain engine); what it says travels with each ProxyState
        self.advice = advice
        self._target = None        # (ProxyState, lead_s, arrival ns) the tool follows
        self._tpose = np.zeros(7)
        self._ttwist = np.zeros(6)
        self.sent_pose = np.zeros(7)   # tool pose and "touching" of the newest ContactUpdate sent
        self.sent_touching = False
        self.epsilon_used: list = []
        self.pending: list = []
        self.next_ns = 0
        self.started = False
        self.welcomed = False
        self.steps = 0
        self.updates_sent = 0
        #: the server refused the Hello ("Reject CODE: reason"), e.g. a tool the model cannot hold
        self.rejected = ""

    def service(self) -> None:
        now = self.clock.now_ns()
        ep = self.ep
        if not self.started:
            ep.start(now)
            self.started = True
        while (got := self.tr.recv()) is not None:
            ps = ep.receive(got[0], got[1], now)
            if ps is not None:
                adv = self.advice
                self.inbox.append((now + self.lag_ns, ps, None if adv is None else (adv.epsilon_m, adv.lead_s)))
        newest = None
        while self.inbox and self.inbox[0][0] <= now:
            newest = self.inbox.pop(0)
        if newest is not None:
            self.drive(newest[1], newest[2], newest[0])
        ep.poll(now)
        if ep.reject is not None:
            self.rejected = f"Reject {ep.reject.code}: {ep.reject.reason}"
        if ep.established and not self.welcomed:
            self.welcomed = True
            self.engine.set_epsilon(ep.welcome.epsilon_m)
            from ..clients.engine import ContactBuffer

            self.buf = ContactBuffer(ep.welcome.max_contacts)
            self.next_ns = now
        if self.welcomed and now >= self.next_ns:
            eng = self.engine
            self._follow(now)
            dt = eng.next_step_s() or 1.0 / self.info.env_rate_hz
            eng.step(dt)
            n = eng.contacts(self.buf, self.buf.capacity)
            eng.tool_pose(self.pose)
            b = self.buf
            self.misreport.apply(eng.time_s, b.keys, b.normal, n)
            self.sent_touching = bool(n and np.min(b.separation_m[:n]) <= 0.0)
            self.sent_pose[:] = self.pose
            item = (now + self.delay_ns, eng.time_s, self.pose.copy(), b.keys[:n].copy(), b.position_m[:n].copy(),
                    b.normal[:n].copy(), b.separation_m[:n].copy(), b.v_constr_m_per_s[:n].copy())
            self.pending.append(item)
            self.steps += 1
            self.next_ns = now + int(round(dt * _NS))
        while self.pending and self.pending[0][0] <= now:
            _, t_env, pose, k, p, nrm, d, vc = self.pending.pop(0)
            if ep.established:
                ep.send_contacts(now, t_env, pose, k, p, nrm, d, vc)
                self.updates_sent += 1

    def drive(self, ps, advice=None, at_ns: int = 0) -> None:
        """Drive the engine's tool towards the newest ProxyState (as the client runner does);
        with the server's ``advice`` (epsilon, lead): inflate the tool by that epsilon and track
        the proxy's pose advanced by the lead (plus the time since it arrived: ``_follow``)."""
        if advice is None:
            self.engine.drive_tool(ps.proxy_pose, ps.proxy_twist, ps.wrench)
            return
        eps, lead = advice
        if self.advice.predict:
            self.engine.set_epsilon(eps)
            self.epsilon_used.append(eps)
        self._target = (ps, lead, at_ns)
        self._follow(at_ns)

    def _follow(self, now: int) -> None:
        if self._target is None:
            return
        ps, lead, at = self._target
        ahead = lead + (now - at) * 1e-9 if lead > 0 else 0.0
        advance_pose(ps.proxy_pose, ps.proxy_twist, ahead, self._tpose)
        self.engine.drive_tool(self._tpose, ps.proxy_twist, ps.wrench)

    def close(self) -> None:
        self.tr.close()


def run_simulated(spec: RunSpec, *, record_penalty: bool = True, model_timing_every: int = 0,
                  folder: Path | None = None) -> Trace:
    """Run ``spec`` in simulated time in this process (see the module docstring).

    ``model_timing_every`` > 0: every that many steps, time the model kernel alone (numba
    ``step_rigid``) and the plain-numpy reference step on copies of the live arrays with the
    step's hand wrench (the numba vs numpy cost on the run's own states)."""
    from ..server import config as cfgmod
    from ..server import passivity as pv
    from ..server.clock import SimClock
    from ..server.loop import HapticLoop

    url = f"mem://experiment-{next(_mem_names)}"
    with tempfile.TemporaryDirectory(prefix="hapticproxy-exp-") as tmp:
        folder = Path(folder or tmp)
        settings = cfgmod.load(spec.settings_dict(url, 1, folder))
        clock = SimClock(start_ns=_NS)
        loop = HapticLoop.build(settings, clock=clock)
    _configure_models(loop, spec)
    env = None
    try:
        loop.warm_up()
        loop.start()
        advice = _advice(spec) if (spec.predict_epsilon or spec.lead) else None
        env = SimEnvClient(spec.make_engine(), url, clock, scene=spec.scene, epsilon_m=spec.epsilon_m,
                           max_contacts=spec.capacity, delay_s=spec.env_delay_s,
                           misreport=Misreport(spec.misreport, spec.misreport_from_s, spec.misreport_every),
                           tool_lag_s=spec.tool_lag_s, advice=advice)
        n_steps = int(round((spec.hand.start_s + spec.seconds) * settings.rate_hz))
        step_ns = np.zeros(n_steps, dtype=np.int64)
        hd = 3
        pen = np.zeros((n_steps, hd)) if record_penalty else None
        upd = np.zeros(n_steps, dtype=bool)
        recovering = np.zeros(n_steps, dtype=np.int64)
        rec_step = np.zeros(n_steps)
        numba_us: list[float] = []
        numpy_us: list[float] = []
        rows = np.zeros((n_steps, loop.shared.ring.shape[1]))
        sh = loop.shared
        perf = time.perf_counter_ns
        last_updates = 0
        crash = ""
        for i in range(n_steps):
            env.service()
            if model_timing_every and loop._margs is not None and i % model_timing_every == 0:
                a, b = _time_model_step(loop)
                numba_us.append(a)
                numpy_us.append(b)
            t0 = perf()
            try:
                loop.step()
            except Exception as exc:  # noqa: BLE001 - the server loop itself failed: recorded, the run ends
                crash = f"{type(exc).__name__}: {exc}"
                n_steps = i
                break
            step_ns[i] = perf() - t0
            rows[i] = sh.ring[(int(sh.head[0]) - 1) % sh.ring_rows]
            if loop.updates != last_updates:
                upd[i] = True
                last_updates = loop.updates
                if advice is not None and loop.model is not None:
                    # what the loop does after applying an update: tell the advice (the ProxyState
                    # of this step carries its epsilon and lead)
                    hs = loop.model.hand_state()
                    advice.on_update(clock.now_ns() * 1e-9, hs[:7], hs[7:13], env.sent_pose, env.sent_touching)
            if loop.model is not None:
                recovering[i] = loop.model.recovering
                rec_step[i] = loop.model.recovery_force_step_n
                if pen is not None:
                    pen[i] = loop.model.penalty_wrench[:hd]
        rows, step_ns, pen, upd = rows[:n_steps], step_ns[:n_steps], (None if pen is None else pen[:n_steps]), upd[:n_steps]
        recovering, rec_step = recovering[:n_steps], rec_step[:n_steps]
        if crash and not np.any(rows[:, TEL_UPDATES] > 0):
            raise RunFailed(f"the server loop failed before the client engaged it: {crash}", crash)
        if env.rejected and not np.any(rows[:, TEL_UPDATES] > 0):
            raise RunFailed(f"the server refused the session: {env.rejected}", env.rejected)
        snap = sh.snapshot()
        counters = loop.ctrl.counters()
        tr = trace_from_rows(
            spec, "simulated", rows, rate_hz=settings.rate_hz, achieved_rate_hz=settings.rate_hz,
            env_rate_hz=float(snap["env_rate_hz"]), faults=int(loop.faults_total) + (1 if crash else 0),
            model_nonfinite=int(loop.model.counters()["nonfinite"]) if loop.model is not None else 0,
            rate_limited=counters["rate_limited"], saturated=counters["saturated"],
            per_step={"step_us": step_ns / 1e3, "penalty": pen, "update_step": upd, "recovering": recovering,
                      "recovery_step_n": rec_step},
            model_numba_us=np.array(numba_us) if numba_us else None,
            model_numpy_us=np.array(numpy_us) if numpy_us else None,
            extra={"loop_exception": crash, "env_steps": env.steps, "updates_sent": env.updates_sent,
                   "misreported_updates": env.misreport.applied,
                   "recovery_energy_j": loop.model.recovery_energy_j if loop.model is not None else 0.0,
                   "touching_contacts": int(np.sum(loop.model.proxy_separations() <= 0.0)) if loop.model else 0,
                   "advice": None if advice is None else {
                       "epsilon_mm": [round(min(env.epsilon_used, default=0.0) * 1e3, 3),
                                      round(max(env.epsilon_used, default=0.0) * 1e3, 3)],
                       "distance_mm": round(advice.distance_m * 1e3, 3),
                       "lead_ms": round(advice.lead_s * 1e3, 2), "lag_ms": round(advice.lag_s * 1e3, 2),
                       "lag_samples": advice.lag_samples},
                   "loop_updates": loop.updates, "passivity_limited": int(counters["passivity_limited"]),
                   "tank_low_j": float(loop.ctrl.ts[pv.TS_LOW]),
                   "update_errors": loop.update_errors, "model": loop.model.counters() if loop.model else {}})
        return tr
    finally:
        if env is not None:
            env.close()
            env.engine.close()
        loop.close()


def _advice(spec: RunSpec):
    """The server's EngineAdvice for this run's tool (the granted epsilon is its cap)."""
    from ..server.prediction import EngineAdvice, tool_radius_m

    eng = spec.make_engine()
    try:
        tool = eng.load_scene(spec.scene).tool
    finally:
        eng.close()
    ixx, iyy, izz = tool.inertia_kg_m2[:3]
    r = tool_radius_m(tool.mass_kg, (ixx, iyy, izz) if tool.kind != "planar" else (izz,))
    r += float(np.linalg.norm(tool.com_m))
    cap = 0.0 if spec.policy == "lm0" else spec.epsilon_m
    return EngineAdvice(cap, tool_radius_m=r, predict=spec.predict_epsilon, lead=spec.lead)


def _configure_models(loop, spec: RunSpec) -> None:
    """Apply the spec's model options to every LocalModel the loop builds for a session (the
    loop builds it from the client's Hello; its config has no keys for these yet)."""
    if not spec.recovery and not spec.reading:
        return
    if spec.reading not in ("", "paper-literal"):
        raise ValueError(f"reading: expected '' or 'paper-literal', got {spec.reading!r}")
    build = loop.models.build
    rec = dict(spec.recovery)

    def new_model(hello, epsilon_m, max_contacts):
        tool, model = build(hello, epsilon_m, max_contacts)
        if spec.reading == "paper-literal":
            model.read_eq6_literally()
            return tool, model
        cur = model.recovery
        if "speed_m_per_s" in rec and "normal_speed_max_m_per_s" not in rec:
            cur["normal_speed_max_m_per_s"] = None      # follows the speed
        cur.update(rec)
        model.set_recovery(cur["speed_m_per_s"], cur["force_rate_n_per_s"], cur["tau_s"], int(cur["min_age_updates"]),
                           cur["normal_speed_max_m_per_s"])
        return tool, model

    loop.models.build = new_model  # the check and the engagement both build through it


def _time_model_step(loop) -> tuple[float, float]:
    """One model step timed twice on copies of the live state: the numba kernel and the numpy
    reference (same inputs; neither touches the loop's model)."""
    from ..server.model.kernels import step_rigid
    from ..server.model.reference import reference_step

    kind, par, st, C, CI, cnt, wk = loop._margs
    hand = loop.ctrl.hand.copy()
    st1, C1, CI1, cnt1, wk1 = st.copy(), C.copy(), CI.copy(), cnt.copy(), wk.copy()
    t0 = time.perf_counter_ns()
    step_rigid(kind, par, st1, C1, CI1, cnt1, wk1, hand)
    t1 = time.perf_counter_ns()
    reference_step(kind, par, st.copy(), C.copy(), CI.copy(), cnt.copy(), hand)
    t2 = time.perf_counter_ns()
    return (t1 - t0) / 1e3, (t2 - t1) / 1e3


# ------------------------------------------------------------------------------ real time
def run_realtime(spec: RunSpec, *, log=None, connect_timeout_s: float = 30.0) -> Trace:
    """Run ``spec`` on the real server process and a real client over UDP on 127.0.0.1."""
    if spec.recovery or spec.misreport or spec.tool_lag_s or spec.predict_epsilon or spec.lead or spec.reading:
        raise ValueError("recovery / misreport / tool_lag_s: simulated time only (the real-time server takes its "
                         "[model] config)")
    from ..clients.runner import ClientRunner
    from ..server import config as cfgmod
    from ..server.daemon import Supervisor

    url = f"udp://127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="hapticproxy-exp-") as tmp:
        settings = cfgmod.load(spec.settings_dict(url, None, Path(tmp)))
        sup = Supervisor(settings)
        eng = spec.make_engine()
        stop = threading.Event()
        relay = None
        client_url = url
        if spec.env_delay_s > 0:
            from ..testing.impair import ImpairingRelay, Impairment

            host, _, port = url.removeprefix("udp://").rpartition(":")
            relay = ImpairingRelay((host, int(port)), c2s=Impairment(delay_s=float(spec.env_delay_s)))
            client_url = relay.url
        runner = ClientRunner(eng, client_url, scene=spec.scene, epsilon_m=spec.epsilon_m,
                              max_contacts=spec.capacity, connect_timeout_s=connect_timeout_s)
        err: list[BaseException] = []

        def client():
            try:
                runner.run(stop)
            except BaseException as exc:  # noqa: BLE001 - re-raised below
                err.append(exc)

        th = threading.Thread(target=client, name="experiment-client", daemon=True)
        try:
            sup.start()
            if relay is not None:
                relay.start()
            th.start()
            total = spec.hand.start_s + spec.seconds
            t0 = time.monotonic()
            while not err:
                sup._serve_status(0.05)
                snap_t = sup.shared.status[sup._st("t_last_ns")] - sup.shared.status[sup._st("t_start_ns")]
                if snap_t * 1e-9 >= total or time.monotonic() - t0 > total + connect_timeout_s:
                    break
            snap = sup.shared.snapshot()
            head = int(sup.shared.head[0])
            n = min(head, sup.ring_rows)
            rows = sup.shared.ring[np.arange(head - n, head) % sup.ring_rows].copy()
        finally:
            stop.set()
            if th.ident is not None:
                th.join(10)
            try:
                sup.close()
            finally:
                eng.close()
                if relay is not None:
                    relay.close()
    if err:
        raise RuntimeError(f"environment client failed: {err[0]}")
    span = (snap["t_last_ns"] - snap["t_start_ns"]) * 1e-9
    achieved = (snap["steps"] - 1) / span if span > 0 else 0.0
    from ..server.shm import TEL

    first = rows[rows[:, TEL["updates"]] > 0]
    if len(first) and first[0, TEL["t_s"]] >= spec.hand.start_s:
        raise RuntimeError(f"the client engaged {first[0, TEL['t_s']]:.2f} s after the loop started, after the "
                           f"hand ({spec.hand.start_s:g} s): raise hand.start_s")
    return trace_from_rows(
        spec, "realtime", rows, rate_hz=settings.rate_hz, achieved_rate_hz=achieved,
        env_rate_hz=float(snap["env_rate_hz"]), faults=int(snap["faults_total"]),
        model_nonfinite=int(snap["model_nonfinite"]), rate_limited=int(snap["rate_limited"]),
        saturated=int(snap["saturated"]), compute_us=snap["compute_us"], lateness_us=snap["lateness_us"],
        extra={"client": {k: v for k, v in runner.stats().items() if isinstance(v, (int, float, str))},
               "missed_deadlines": int(snap["missed_deadlines"]), "overruns": int(snap["overruns"]),
               "rt_scheduling": bool(snap["rt_scheduling"]), "updates": int(snap["updates"])})


def run(spec: RunSpec, mode: str, **kw) -> Trace:
    if mode == "realtime":
        return run_realtime(spec, **kw)
    if mode == "simulated":
        return run_simulated(spec, **kw)
    raise ValueError(f"mode: expected realtime or simulated, got {mode!r}")
