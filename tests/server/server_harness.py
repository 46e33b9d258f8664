"""Harness for server-loop tests in simulated time: a scriptable point device, an analytic wall
environment that speaks the real protocol over the in-memory transport, and a loop factory.

Everything runs in one thread on a ``SimClock``, so a test is deterministic: the environment
steps at its own (variable) rate in simulated time, between haptic steps. (Also: stopping a
command a test started, ``stop_process``.)
"""
from __future__ import annotations

import itertools
import math
import signal
from dataclasses import dataclass

import numpy as np
import pytest

from hapticproxy.protocol.messages import ToolKind
from hapticproxy.protocol.codec import Hello
from hapticproxy.protocol.session import ClientEndpoint
from hapticproxy.protocol.transport import open_transport
from hapticproxy.server import config as cfg
from hapticproxy.server.clock import SimClock
from hapticproxy.server.devices.base import (
    DEV_FAULT_DISABLED, DEV_FAULT_NONFINITE_COMMAND, DEV_FAULT_WATCHDOG, DEV_OK, DeviceDriver, DeviceLimits,
    empty_state,
)
from hapticproxy.server.loop import HapticLoop
from hapticproxy.testing.cleanup import made_then_ended

_names = itertools.count(1)


def stop_process(proc) -> str:
    """SIGTERM a command started with stderr piped (if it still runs), wait for it (killed if
    it outlives 30 s of waiting); returns its stderr."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    return err


@dataclass(frozen=True)
class PointMass:
    """A :class:`PointDevice`'s handle: mass and inertia, viscous damping of translation [N s/m]
    and of rotation [N m s/rad]."""

    mass_kg: float = 0.5
    inertia_kg_m2: float = 5e-4
    damping: float = 2.0
    rot_damping: float = 0.002

    def acceleration(self, force, v):
        """(ax, ay, alpha) of the handle moving at ``v`` under the net wrench ``force`` (fx, fy, tz):
        M a = F - B v."""
        return np.array([(force[0] - self.damping * v[0]) / self.mass_kg,
                         (force[1] - self.damping * v[1]) / self.mass_kg,
                         (force[2] - self.rot_damping * v[2]) / self.inertia_kg_m2])


class PointDevice(DeviceDriver):
    """A point-mass device (1dof along x, or planar x, y, theta) with a scripted hand force.

    ``hand(t) -> (fx, fy, tz)`` is the user's wrench; the device integrates the handle's
    :class:`PointMass` dynamics (``mass_kg`` ... ``rot_damping``) with semi-implicit Euler at
    ``period_s``. ``read`` and ``write`` return what a real driver (the ``sim`` one) returns: the
    latched fault if any, else ``DEV_FAULT_DISABLED`` while disabled, else ``DEV_OK``.
    """

    name = "point"

    def __init__(self, kind="planar", mass_kg=0.5, inertia_kg_m2=5e-4, damping=2.0, rot_damping=0.002,
                 period_s=1e-3, hand=None, pose=(0.0, 0.0, 0.0), limits=None):
        self.kind = kind
        self.body = PointMass(mass_kg, inertia_kg_m2, damping, rot_damping)
        self.dt = period_s
        self.hand = hand or (lambda t: (0.0, 0.0, 0.0))
        self.x = np.array(pose, dtype=float)  # x, y, theta
        self.v = np.zeros(3)
        self.t = 0.0
        self._limits = limits or DeviceLimits(40.0, 2.0, 5.0, 100.0)
        self._enabled = False
        self._fault = DEV_OK
        self.commands = []  # every wrench actually rendered (after the driver's own checks)
        self.nan_state_at = None  # step index at which read() reports NaN, for fault tests

    @property
    def limits(self):
        return self._limits

    def enable(self):
        self._enabled = True
        self._fault = DEV_OK

    def disable(self):
        self._enabled = False

    @property
    def enabled(self):
        return self._enabled

    @property
    def fault(self):
        return self._fault

    def read(self, s):
        th = self.x[2]
        s[0], s[1], s[2] = self.x[0], self.x[1], 0.0
        s[3], s[4], s[5], s[6] = math.cos(th / 2), 0.0, 0.0, math.sin(th / 2)
        s[7], s[8], s[9] = self.v[0], self.v[1], 0.0
        s[10], s[11], s[12] = 0.0, 0.0, self.v[2]
        fx, fy, tz = self.hand(self.t)
        s[13:19] = (fx, fy, 0.0, 0.0, 0.0, tz)
        s[19] = self.t
        if self.nan_state_at is not None and len(self.commands) >= self.nan_state_at:
            s[0] = math.nan
        return self.status()

    def status(self) -> int:
        """The latched fault, else ``DEV_FAULT_DISABLED`` while disabled, else ``DEV_OK``."""
        if self._fault != DEV_OK:
            return self._fault
        return DEV_OK if self._enabled else DEV_FAULT_DISABLED

    def write(self, w):
        if not np.all(np.isfinite(w)):
            self._fault = DEV_FAULT_NONFINITE_COMMAND
        f = np.array([w[0], w[1], w[5]]) if (self._enabled and self._fault == DEV_OK) else np.zeros(3)
        if self.kind == "1dof":
            f[1] = f[2] = 0.0
        self.commands.append(f.copy())
        fx, fy, tz = self.hand(self.t)
        h = np.array([fx, fy, tz])
        if self.kind == "1dof":
            h[1] = h[2] = 0.0
        acc = self.body.acceleration(h + f, self.v)
        self.v += self.dt * acc
        self.x += self.dt * self.v
        self.t += self.dt
        return self.status()


class WatchdogDevice(PointDevice):
    """A ``PointDevice`` that lives in real (simulated) time like hardware: its own watchdog cuts
    the output when no ``write`` came within ``watchdog_s`` (latched until ``enable``), and a gap
    between writes (a stall of the loop) is integrated too, the hand pushing on a handle that
    renders nothing. ``clock``: the loop's clock."""

    def __init__(self, clock, *, watchdog_s=0.05, **kw):
        super().__init__(**kw)
        self.clock = clock
        self.wd_ns = int(round(watchdog_s * 1e9))
        self._last_ns = None
        self._limits = DeviceLimits(40.0, 2.0, 5.0, 100.0, watchdog_s=watchdog_s)
        self.trips = 0

    def enable(self):
        super().enable()
        self._last_ns = self.clock.now_ns()

    def _check(self):
        now = self.clock.now_ns()
        if (self._enabled and self._fault == DEV_OK and self._last_ns is not None
                and now - self._last_ns > self.wd_ns):
            self._fault = DEV_FAULT_WATCHDOG
            self.trips += 1
        return now

    def read(self, s):
        self._check()
        return super().read(s)

    def write(self, w):
        now = self._check()
        if self._last_ns is not None:
            # the time the loop did not run: the hand moved the handle, nothing was rendered
            extra = int((now - self._last_ns) // int(self.dt * 1e9)) - 1
            for _ in range(max(0, extra)):
                en, self._enabled = self._enabled, False
                PointDevice.write(self, np.zeros(6))
                self.commands.pop()
                self._enabled = en
        self._last_ns = now
        return super().write(w)


def contact_arrays(keys, pos, nor, sep):
    """The (keys, points, normals, separations, normal speeds) arrays ``send_contacts`` takes, from
    per-contact lists; every contact at rest (zero normal speed)."""
    n = len(keys)
    return (np.array(keys, dtype=np.int64).reshape(n, 3), np.array(pos, dtype=float).reshape(n, 3),
            np.array(nor, dtype=float).reshape(n, 3), np.array(sep, dtype=float), np.zeros(n))


class ProtocolEnv:
    """An environment client speaking the real protocol over the in-memory transport, in simulated
    time. A subclass follows each ProxyState (``_follow``), sends its ContactUpdate (``_send``) and
    says when the next one is due (``_next_ns``)."""

    def __init__(self, url, clock, hello):
        self.tr = open_transport(url, "client")
        self.clock = clock
        self.hello = hello
        self.ep = ClientEndpoint(self.tr.send, self.hello)
        self.next_ns = 0
        self.updates_sent = 0
        self.proxy_states = 0
        self.last_proxy = None
        self.alive = True
        self.started = False

    def service(self):
        """Receive everything waiting; on the env's own schedule, step and send contacts."""
        if not self.alive:
            return
        now = self.clock.now_ns()
        if not self.started:
            self.ep.start(now)
            self.started = True
            self.next_ns = now
        while True:
            item = self.tr.recv()
            if item is None:
                break
            ps = self.ep.receive(item[0], item[1], now)
            if ps is not None:
                self.proxy_states += 1
                self.last_proxy = ps
                self._follow(ps)
        self.ep.poll(now)
        if now >= self.next_ns and self.ep.established:
            self._send(now)
            self.updates_sent += 1
            self.next_ns = self._next_ns(now)

    def kill(self):
        """Vanish without a Bye (a killed process)."""
        self.alive = False

    def bye(self):
        self.ep.close(now_ns=self.clock.now_ns())
        self.alive = False

    def close(self):
        self.tr.close()


class WallEnv(ProtocolEnv):
    """Environment client: a planar box tool (half sizes ``hx``, ``hy``) and a floor at y = ``wall_y``
    (normal +y). The engine's tool follows the proxy pose it last received (kinematic drive).
    Reports the two bottom corners within ``epsilon`` of the floor. Steps at ``rate_hz`` with an
    optional jitter pattern, in simulated time."""

    def __init__(self, url, clock, *, hx=0.02, hy=0.01, wall_y=0.0, epsilon=0.005, rate_hz=60.0,
                 jitter=0.0, start_pose=(0.0, 0.05, 0.0), mass_kg=0.2, inertia=2e-4, kind="planar", seed=1,
                 rigid=True):
        self.rigid = rigid  # True: the engine's tool is held at the floor; False: kinematic, penetrates
        self.hx, self.hy, self.wall_y, self.eps = hx, hy, wall_y, epsilon
        self.rate_hz = rate_hz
        self.jitter = jitter
        self.rng = np.random.default_rng(seed)
        self.pose = np.array([start_pose[0], start_pose[1], 0.0, math.cos(start_pose[2] / 2), 0, 0,
                              math.sin(start_pose[2] / 2)])
        self.kind = kind
        self.hz = hx  # spatial: a box hx x hy x hx (half sizes)
        tk = {"planar": ToolKind.PLANAR, "1dof": ToolKind.ONE_DOF, "spatial": ToolKind.SPATIAL}[kind]
        axis = (0.0, 1.0, 0.0) if kind == "1dof" else (1.0, 0.0, 0.0)
        super().__init__(url, clock, Hello(client_nonce=1, engine="wall-env", tool_kind=tk, mass_kg=mass_kg,
                                           inertia_kg_m2=(inertia, inertia, inertia, 0, 0, 0), axis=axis,
                                           max_contacts=8, epsilon_m=epsilon, env_rate_hz=rate_hz))

    def _corners(self):
        """World (x, y, z) of the tool's bottom corners (planar/1dof: two, spatial: four)."""
        w, qx, qy, qz = self.pose[3:7]
        R = np.array([[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)],
                      [2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)],
                      [2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)]])
        if self.kind == "spatial":
            body = [(sx * self.hx, -self.hy, sz * self.hz) for sx in (-1, 1) for sz in (-1, 1)]
        else:
            body = [(-self.hx, -self.hy, 0.0), (self.hx, -self.hy, 0.0)]
        return [self.pose[:3] + R @ np.array(b) for b in body]

    def _stop_at_wall(self):
        # the engine's tool cannot enter the floor (a rigid engine resolves that itself)
        low = min(p[1] for p in self._corners())
        if low < self.wall_y:
            self.pose[1] += self.wall_y - low

    def contacts(self):
        keys, pos, nor, sep = [], [], [], []
        for i, p in enumerate(self._corners()):
            x, y, z = p
            d = y - self.wall_y
            if d <= self.eps:
                keys.append((0, 1, i))
                pos.append((x, self.wall_y, z))
                nor.append((0.0, 1.0, 0.0))
                sep.append(d)
        return contact_arrays(keys, pos, nor, sep)

    def _follow(self, ps):
        self.pose = np.array(ps.proxy_pose, dtype=float)
        if self.rigid:
            self._stop_at_wall()

    def _send(self, now):
        k, p, n, d, v = self.contacts()
        self.ep.send_contacts(now, now * 1e-9, self.pose, k, p, n, d, v)

    def _next_ns(self, now):
        period = 1.0 / self.rate_hz
        if self.jitter:
            period *= 1.0 + self.jitter * (2 * self.rng.random() - 1)
        return now + int(period * 1e9)


def make_settings(**sections):
    base = {"loop": {"rate_hz": 1000.0}, "transport": {"url": f"mem://loop-test-{next(_names)}"},
            "device": {"driver": "sim", "kind": "planar"}, "telemetry": {"ring_s": 2.0}}
    for k, v in sections.items():
        base.setdefault(k, {}).update(v)
    return cfg.load(base)


class Rig:
    """A loop + device + wall environment in simulated time."""

    def __init__(self, settings, device, env_kwargs=None, clock=None):
        self.clock = clock or SimClock(start_ns=1_000_000_000)
        self.settings = settings
        self.device = device
        self.loop = HapticLoop.build(settings, clock=self.clock, device=device)
        self.loop.warm_up()
        self.loop.start()
        self.env = WallEnv(settings["transport"]["url"], self.clock, **(env_kwargs or {}))
        self.rows = []

    def run(self, seconds, record=True, on_step=None):
        n = int(round(seconds * self.settings.rate_hz))
        first = len(self.rows)
        for i in range(n):
            self.env.service()
            alive = self.loop.step()
            if record:
                self.rows.append(self.loop.shared.ring[(int(self.loop.shared.head[0]) - 1) % self.loop.shared.ring_rows].copy())
            if on_step is not None:
                on_step(i)
            if not alive:
                break
        return np.array(self.rows[first:])

    def close(self):
        self.env.close()
        self.loop.close()


def _rig(settings=None, device=None, env_kwargs=None, **sections):
    s = settings or make_settings(**sections)
    dev = device or PointDevice(kind=s["device"]["kind"], period_s=s.period_ns * 1e-9)
    return Rig(s, dev, env_kwargs)


@pytest.fixture
def rig_factory():  # re-exported by conftest.py
    yield from made_then_ended(_rig)


def random_contacts(rng, n, planar=False, links=1):
    """n valid contacts: keys (tool link below ``links``, body, feature), positions, unit normals
    (in the x-y plane if ``planar``), separations, constraint velocities."""
    keys = np.zeros((n, 3), dtype=np.int64)
    if links > 1:
        keys[:, 0] = rng.integers(0, links, n)
    keys[:, 1] = rng.integers(0, 5, n)
    keys[:, 2] = np.arange(n)
    normal = rng.normal(size=(n, 3))
    if planar:
        normal[:, 2] = 0.0
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    pos = rng.uniform(-0.2, 0.2, (n, 3))
    sep = rng.uniform(-0.005, 0.01, n)
    vc = rng.uniform(-0.5, 0.5, n)
    return keys, pos, normal, sep, vc


def break_contact_rule(case: str, rng, i: int, keys, pos, normal, sep, vc) -> bool:
    """Make contact ``i`` break the codec's rule that ``case`` names, or sit at its edge
    (``at_max``, ``unit_edge_in``: still valid); ``False`` if ``case`` names no such rule."""
    from hapticproxy.protocol.messages import MAX_ABS_FLOAT, UNIT_TOLERANCE

    if case == "nan":
        [pos, normal, sep, vc][int(rng.integers(0, 4))].reshape(-1)[0] = np.nan
    elif case == "inf":
        vc[i] = -np.inf
    elif case == "big":
        sep[i] = MAX_ABS_FLOAT * (1 + 1e-15)
    elif case == "at_max":
        pos[i, 0] = MAX_ABS_FLOAT
    elif case == "not_unit":
        normal[i] *= 1.01
    elif case == "unit_edge_in":
        normal[i] *= 1.0 + UNIT_TOLERANCE * (1 - 1e-9)
    elif case == "unit_edge_out":
        normal[i] *= 1.0 - UNIT_TOLERANCE * (1 + 1e-9)
    elif case in ("duplicate", "many_duplicate"):
        if len(keys) > 1:
            keys[-1] = keys[0]
    else:
        return False
    return True


def receive_update(rig, tries: int = 200):
    """The engine's next update, received (decoded) as the Python side beside a ticking thread
    does, without a step: the ContactUpdate now pending (``rig.loop.proto._pending``)."""
    lp = rig.loop
    for _ in range(tries):
        rig.env.service()
        rig.clock.advance(lp.period_ns)
        lp.proto.poll(rig.clock.now_ns())
        if lp.proto._pending is not None:
            return lp.proto._pending
    raise AssertionError("no update")


def tick_once(loop, now: int) -> int:
    """One tick as a clock thread runs it (its lock aside), ending at ``now``; its packed results."""
    from hapticproxy.server import tick

    loop.tk[tick.TK_SIMULATED] = 1
    loop.tk[tick.TK_SIM_COST_NS] = 0
    return tick.tick_at(loop._desc_addr, now, 0)
