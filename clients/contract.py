"""The engine contract: what every engine promises the runner and the server, as a pytest suite
shipped in the package so that a lab runs it against its own engine (python-can's back-to-back
test is the model: one test class, a subclass per backend).

In a lab's own package, with its engine registered (``[project.entry-points."hapticproxy.engines"]
mylab = "mylab.engine:MyLabEngine"``)::

    # tests/test_contract.py
    from .contract import EngineContract

    class TestMyLabEngine(EngineContract):
        engine = "mylab"                      # the registry name
        engine_kwargs = {"seed": 1}           # optional: constructor arguments
        # or override make_engine(self) to build it yourself

then ``pytest`` (the module needs pytest: the ``test`` extra). hapticproxy runs the same class
against every registered engine
(``tests/clients/test_contract.py``). Every scene of the engine (``scenes``: a subset) is run
**in simulated time**, in one thread: a :class:`ClientRunner` paced by a :class:`SimClock` against
a :class:`ScriptedServer` (the protocol's ``ServerEndpoint`` on the in-memory transport, answering
every ContactUpdate with a scripted ProxyState), so results never depend on the machine's speed.

What is checked (each test names the scene that broke it):

1. **Scene description**: every scene loads, ``load_scene`` refuses an unknown name with
   ``ValueError``, the Hello built from the scene encodes, decodes and opens a session with the
   server (its ``hello_check``, when a subclass sets one, too), the start pose is a unit
   pose.
2. **Rate**: with the proxy held at the start pose for :attr:`EngineContract.rate_seconds`, one
   ContactUpdate per step, engine time increasing, the engine's clock keeping up with the
   (simulated) wall clock, a fixed-rate engine stepping exactly ``1 / env_rate_hz``, a
   variable-rate one within half to twice its declared rate on average.
3. **Contacts** along the probe (below), with the server granting :attr:`grant_contacts`: never
   more than granted, unit normals, unique keys, finite numbers, separations within the granted
   epsilon, nothing refused by the server, and some contacts at all (a probe that finds none says
   so: set :attr:`probe_m`).
4. **Following**: the probe drives the proxy from the start pose along each axis the tool kind
   can move along, out and back, once for each distance in :attr:`probe_m` (ramps of
   :attr:`probe_ramp_s`, holds of :attr:`probe_hold_s`). At the end of every hold the tool is at the proxy (within
   :attr:`follow_tol_m` and :attr:`follow_tol_rad`) unless it reports contacts (something is in
   the way), and at least one leg is followed.
5. **Holding**: while the server reports the proxy as not rendered (``FAULT``) the tool stays where
   it was although the scripted proxy moves on, and it follows again once ``ENGAGED``.
6. **Determinism**: an engine whose class says ``deterministic = True`` gives the very same
   ContactUpdates, bit for bit, on a second run of the probe's first legs with a fresh engine.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from ..protocol.codec import Codec, Hello
from ..protocol.messages import ServerState
from ..protocol.session import ServerConfig, ServerEndpoint
from ..protocol.transport import open_transport

from .engine import Engine
from .geometry import quat_angle
from .registry import availability, load_engine_class
from .runner import TOOL_KINDS, ClientRunner, hello_fields

__all__ = ["EngineContract", "ProxyCommand", "ScriptedServer", "SimClock", "simulate"]

_NS = 1_000_000_000
_names = itertools.count(1)


# ---------------------------------------------------------------------------------------- tools
class SimClock:
    """A clock [ns] that only moves when told (``clock()`` reads it)."""

    def __init__(self, start_ns: int = _NS) -> None:
        self.now_ns = int(start_ns)

    def __call__(self) -> int:
        return self.now_ns

    def advance(self, seconds: float) -> None:
        self.now_ns += int(round(seconds * _NS))


@dataclass
class ProxyCommand:
    """What the scripted server sends in its next ProxyState."""

    pose: np.ndarray
    twist: np.ndarray = field(default_factory=lambda: np.zeros(6))
    wrench: np.ndarray = field(default_factory=lambda: np.zeros(6))
    joint_position: np.ndarray = field(default_factory=lambda: np.zeros(0))
    joint_velocity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    server_state: int = ServerState.ENGAGED
    epsilon_m: float = 0.0  # the advice (protocol 1.2): 0 is none
    lead_s: float = 0.0


class ScriptedServer:
    """The protocol's ``ServerEndpoint`` on an in-memory transport, in simulated time.

    Every ContactUpdate it accepts is recorded (``updates``: ``(server time s, update)``, the
    time since the session opened) and answered with ``script(t, server)``'s
    :class:`ProxyCommand` (``None``: no answer). ``start_pose`` / ``start_joints`` hold the
    engine's tool pose (and joints) of the session's first update, for scripts relative to it.
    ``sleep(s)`` advances the clock and serves: hand it to the runner as its ``sleep``."""

    def __init__(self, clock: SimClock, script, *, config: ServerConfig | None = None, hmac_key: bytes | None = None,
                 name: str | None = None) -> None:
        self.clock = clock
        self.script = script
        self.url = f"mem://{name or f'contract-{next(_names)}'}"
        self.transport = open_transport(self.url, role="server")
        self.endpoint = ServerEndpoint(self.transport.send, config, hmac_key=hmac_key)
        self.updates: list = []
        self.start_pose: np.ndarray | None = None
        self.start_joints: np.ndarray | None = None

    def service(self) -> None:
        now = self.clock()
        ep = self.endpoint
        for data, peer in self.transport.drain():
            upd = ep.receive(data, peer, now)
            if upd is None:
                continue
            s = ep.sessions.get(upd.session_id)
            t = (now - s.opened_ns) / _NS
            self.updates.append((t, upd))
            if self.start_pose is None:
                self.start_pose = np.array(upd.tool_pose, dtype=float)
                joints = getattr(upd, "tool_joint_position", None)
                self.start_joints = np.zeros(0) if joints is None else np.array(joints, dtype=float)
            cmd = self.script(t, self)
            if cmd is not None:
                ep.send_proxy_state(upd.session_id, now, cmd.pose, cmd.twist, cmd.wrench,
                                    joint_position=cmd.joint_position, joint_velocity=cmd.joint_velocity,
                                    joint_effort=np.zeros(len(cmd.joint_position)), server_state=int(cmd.server_state),
                                    epsilon_m=cmd.epsilon_m, lead_s=cmd.lead_s)
        ep.poll(now)

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.clock.advance(seconds)
        self.service()

    def close(self) -> None:
        self.endpoint.close_all(now_ns=self.clock())
        self.transport.close()


def simulate(engine: Engine, scene: str, script, seconds: float, *, config: ServerConfig | None = None,
             epsilon_m: float = 0.005, max_contacts: int = 16, prepare=None,
             **runner_options) -> tuple[ClientRunner, ScriptedServer]:
    """Run ``engine`` in ``scene`` for ``seconds`` of simulated time against a
    :class:`ScriptedServer` playing ``script``; returns the (closed) runner and the server.
    ``prepare(runner)``, when given, is called with the runner before it starts (the scene is
    loaded then) and returns ``(script, seconds)`` to play instead."""
    clock = SimClock()
    holder = {"script": script}
    server = ScriptedServer(clock, lambda t, s: holder["script"](t, s), config=config)
    try:
        options = dict(realtime=True, reconnect=False, connect_timeout_s=5.0)
        options.update(runner_options)
        runner = ClientRunner(engine, server.url, scene=scene, epsilon_m=epsilon_m, max_contacts=max_contacts,
                              clock_ns=clock, sleep=server.sleep, **options)
        if prepare is not None:
            holder["script"], seconds = prepare(runner)
        runner.start()
        end = clock() + int(seconds * _NS)
        passes = 0
        limit = int(seconds * 20_000) + 10_000
        try:
            while clock() < end and not runner.done:
                wait = runner.poll()
                server.sleep(min(wait, 0.002) if wait > 0 else 0.0)
                passes += 1
                if passes > limit:
                    raise AssertionError(f"{scene}: the runner made no progress in simulated time")
        finally:
            runner.close()
            server.service()
    finally:
        server.transport.close()
    return runner, server


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def probe_legs(runner: ClientRunner, distances_m) -> list[np.ndarray]:
    """The probe's displacements (world, m): along every axis the scene's tool may move along (a
    1-DOF tool its axis, a planar tool or a linkage whose joints all turn about z x and y, others
    x, y and z), both ways, by each distance."""
    tool = runner.scene_info.tool
    if tool.kind == "1dof":
        axes = [_unit(tool.axis)]
    elif tool.kind == "planar" or (tool.kind == "linkage" and all(
            abs(abs(float(ln.joint_axis[2])) - 1.0) < 1e-9 and abs(float(ln.joint_origin[2])) < 1e-12
            for ln in tool.links[1:])):
        axes = [np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])]
    else:
        axes = [np.eye(3)[k] for k in range(3)]
    return [dist * s * a for dist in distances_m for a in axes for s in (1.0, -1.0)]


# ---------------------------------------------------------------------------------------- the suite
@dataclass
class _Subject:
    name: str
    cls: type
    kwargs: dict
    scenes: tuple[str, ...]
    make: object


_PROBES: dict = {}


class EngineContract:
    """The contract suite (see the module docstring). Subclass it as ``Test...`` with
    :attr:`engine` set (or :meth:`make_engine` overridden)."""

    #: registry name of the engine under test
    engine: str = ""
    #: constructor arguments of the engine
    engine_kwargs: dict = {}
    #: scenes to run (default: all the engine's)
    scenes: tuple[str, ...] | None = None
    #: the server's own check of a Hello (``hello -> ""`` or the reason to refuse), if any
    hello_check = None
    #: epsilon requested and granted [m]; contact capacity the server grants in the probe
    epsilon_m: float = 0.005
    grant_contacts: int = 3
    #: the probe: how far [m] along each axis (one leg each), ramp and hold durations [s]
    probe_m: tuple[float, ...] = (0.05, 0.15)
    probe_ramp_s: float = 0.4
    probe_hold_s: float = 0.4
    #: how close the tool must come to a proxy it can reach [m, rad]
    follow_tol_m: float = 0.002
    follow_tol_rad: float = 0.05
    #: simulated seconds of the rate test
    rate_seconds: float = 2.0

    def make_engine(self) -> Engine:
        """A fresh engine under test (default: the registry's class with :attr:`engine_kwargs`)."""
        return load_engine_class(self.engine)(**self.engine_kwargs)

    # ------------------------------------------------------------------ fixtures
    @pytest.fixture
    def engine_name(self) -> str:
        if not self.engine:
            pytest.fail(f"{type(self).__name__}: set `engine` to a registered engine name or override make_engine")
        return self.engine

    @pytest.fixture
    def subject(self, engine_name):
        if type(self).make_engine is EngineContract.make_engine:
            why = availability(engine_name)
            if why:
                pytest.skip(why)
            cls = load_engine_class(engine_name)
            kwargs = dict(self.engine_kwargs)

            def make():
                return cls(**kwargs)
        else:
            make = self.make_engine
            probe = make()
            cls, kwargs = type(probe), {}
            probe.close()
        scenes = tuple(self.scenes) if self.scenes else tuple(cls.scenes())
        made = []

        def tracked():
            e = make()
            made.append(e)
            return e

        yield _Subject(engine_name, cls, kwargs, scenes, tracked)
        for e in made:
            e.close()

    # ------------------------------------------------------------------ helpers
    def _config(self, max_contacts: int = 16) -> ServerConfig:
        return ServerConfig(max_epsilon_m=self.epsilon_m, max_contacts=max_contacts, hello_check=self.hello_check)

    def _leg_s(self) -> float:
        return 2.0 * self.probe_ramp_s + 2.0 * self.probe_hold_s

    def _probe_script(self, legs):
        ramp, hold = self.probe_ramp_s, self.probe_hold_s
        leg = self._leg_s()

        def script(t, server):
            k = int(t // leg)
            pose = server.start_pose.copy()
            twist = np.zeros(6)
            if k < len(legs):
                tau = t - k * leg
                d = legs[k]
                if tau < ramp:
                    frac, rate = tau / ramp, 1.0 / ramp
                elif tau < ramp + hold:
                    frac, rate = 1.0, 0.0
                elif tau < 2 * ramp + hold:
                    frac, rate = 1.0 - (tau - ramp - hold) / ramp, -1.0 / ramp
                else:
                    frac, rate = 0.0, 0.0
                pose[:3] += d * frac
                twist[:3] = d * rate
            joints = server.start_joints
            return ProxyCommand(pose, twist, joint_position=joints, joint_velocity=np.zeros(len(joints)))

        return script

    def _probe(self, subject: _Subject, scene: str, fresh: bool = False, legs_run: int | None = None):
        """The probe's run of ``scene`` (cached per engine and scene unless ``fresh``; ``legs_run``:
        only that many legs): (the grants, the server and its record, the legs)."""
        key = (type(self), subject.name, repr(sorted(subject.kwargs.items())), scene)
        if not fresh and key in _PROBES:
            return _PROBES[key]
        legs: list = []

        def prepare(runner):  # the axes depend on the scene's tool, known once the runner loaded it
            legs.extend(probe_legs(runner, self.probe_m))
            n = len(legs) if legs_run is None else min(legs_run, len(legs))
            return self._probe_script(legs), n * self._leg_s() + 0.2

        runner, server = simulate(subject.make(), scene, None, 0.0, config=self._config(self.grant_contacts),
                                  epsilon_m=self.epsilon_m, prepare=prepare)
        # what the checks read, without the engine (closed at the test's end, kept no longer)
        grants = SimpleNamespace(granted_epsilon_m=runner.granted_epsilon_m,
                                 granted_max_contacts=runner.granted_max_contacts)
        out = (grants, server, legs)
        if not fresh:
            _PROBES[key] = out
        return out

    @staticmethod
    def _last_before(server: ScriptedServer, t: float):
        got = None
        for ts, upd in server.updates:
            if ts > t:
                break
            got = upd
        return got

    def _at(self, upd, pose, joints) -> tuple[bool, str]:
        err = float(np.linalg.norm(np.asarray(upd.tool_pose[:3]) - pose[:3]))
        ang = quat_angle(upd.tool_pose[3:7], pose[3:7])
        jerr = 0.0
        tj = getattr(upd, "tool_joint_position", None)
        if joints is not None and len(joints) and tj is not None and len(tj) == len(joints):
            jerr = float(np.max(np.abs(np.asarray(tj) - joints)))
        ok = err <= self.follow_tol_m and ang <= self.follow_tol_rad and jerr <= self.follow_tol_rad
        return ok, f"{err * 1e3:.2f} mm, {ang:.3f} rad" + (f", joints {jerr:.3f} rad" if jerr else "")

    # ------------------------------------------------------------------ 1. scene description
    def test_scenes_describe_a_tool_the_server_accepts(self, subject):
        assert subject.scenes, "the engine has no scenes"
        try:
            subject.make().load_scene("no-such-scene")
        except ValueError:
            pass
        else:
            raise AssertionError("load_scene accepted an unknown scene name (it must raise ValueError)")
        codec = Codec()
        for scene in subject.scenes:
            engine = subject.make()
            info = engine.load_scene(scene)
            assert info.tool.kind in TOOL_KINDS, f"{scene}: tool kind {info.tool.kind!r}"
            assert math.isfinite(info.env_rate_hz) and info.env_rate_hz > 0, f"{scene}: env_rate_hz"
            assert info.tool.mass_kg > 0, f"{scene}: tool mass"
            hello = Hello(client_nonce=7, **hello_fields(engine, info, self.epsilon_m, 16))
            back = codec.decode(codec.encode(hello))
            assert back.tool_kind == hello.tool_kind and len(back.links) == len(hello.links), scene
            pose = engine.tool_pose(np.zeros(7))
            assert np.all(np.isfinite(pose)) and abs(np.linalg.norm(pose[3:7]) - 1.0) < 1e-6, f"{scene}: start pose"
            if info.tool.kind == "linkage":
                assert len(engine.joint_positions(np.zeros(len(info.tool.links) - 1))) == len(info.tool.links) - 1
            runner, server = simulate(subject.make(), scene, lambda t, s: ProxyCommand(s.start_pose), 0.3,
                                      config=self._config(), epsilon_m=self.epsilon_m)
            st = runner.stats()
            assert st["sessions"] == 1 and st["error"] is None, f"{scene}: no session: {st['error']} {st['end_reason']}"
            assert server.endpoint.counters.rejects_sent == 0, f"{scene}: the server refused the Hello"
            assert st["updates_sent"] > 0 and len(server.updates) == st["updates_sent"], scene

    # ------------------------------------------------------------------ 2. rate
    def test_steps_at_its_declared_rate_in_simulated_time(self, subject):
        for scene in subject.scenes:
            engine = subject.make()
            T = self.rate_seconds
            runner, server = simulate(engine, scene, lambda t, s: ProxyCommand(s.start_pose), T,
                                      config=self._config(), epsilon_m=self.epsilon_m)
            st = runner.stats()
            rate = runner.scene_info.env_rate_hz
            times = np.array([u.env_time_s for _, u in server.updates])
            assert len(times) == st["steps"] > 1, f"{scene}: one ContactUpdate per step"
            dts = np.diff(np.r_[0.0, times])
            assert np.all(dts > 0), f"{scene}: env_time_s must increase"
            # the engine keeps up with the (simulated) wall clock from its first step on
            first_s = server.updates[0][0]
            elapsed = server.updates[-1][0] - first_s
            assert abs((times[-1] - times[0]) - elapsed) <= dts.max() + 0.005, (
                f"{scene}: engine time {times[-1] - times[0]:.3f} s over {elapsed:.3f} s of wall time")
            if engine.next_step_s() is None:
                np.testing.assert_allclose(dts, 1.0 / rate, rtol=1e-9, err_msg=f"{scene}: fixed step 1/env_rate_hz")
            else:
                mean = len(dts) / times[-1]
                assert 0.5 * rate <= mean <= 2.0 * rate, f"{scene}: mean rate {mean:.1f} Hz vs declared {rate:g} Hz"

    # ------------------------------------------------------------------ 3. contacts
    def test_contacts_fit_the_grant_with_unit_normals_and_unique_keys(self, subject):
        for scene in subject.scenes:
            runner, server, _ = self._probe(subject, scene)
            c = server.endpoint.counters
            assert c.decode_errors == 0 and c.errors_sent == 0 and c.capacity_exceeded == 0, (
                f"{scene}: the server refused {c.decode_errors} updates ({c.capacity_exceeded} over the grant; the "
                f"protocol's decoder checks unit normals and unique keys): {c!r}")
            assert runner.granted_max_contacts == self.grant_contacts
            seen = 0
            for t, u in server.updates:
                n = u.n_contacts
                where = f"{scene} at {t:.3f} s"
                assert n <= self.grant_contacts, f"{where}: {n} contacts > granted {self.grant_contacts}"
                pose = np.asarray(u.tool_pose)
                assert np.all(np.isfinite(pose)) and abs(np.linalg.norm(pose[3:7]) - 1.0) <= 1e-6, where
                if not n:
                    continue
                seen += 1
                keys = np.asarray(u.keys).reshape(n, 3)
                assert len({tuple(k) for k in keys.tolist()}) == n, f"{where}: duplicate keys {keys.tolist()}"
                nrm = np.asarray(u.normal).reshape(n, 3)
                assert np.all(np.abs(np.linalg.norm(nrm, axis=1) - 1.0) <= 1e-6), f"{where}: normals not unit"
                for name in ("position_m", "normal", "separation_m", "v_constr_m_per_s"):
                    assert np.all(np.isfinite(np.asarray(getattr(u, name)))), f"{where}: {name} not finite"
                sep = np.asarray(u.separation_m)
                assert np.all(sep <= runner.granted_epsilon_m + 1e-9), f"{where}: a contact beyond epsilon: {sep}"
            assert seen > 0, (f"{scene}: the probe ({', '.join(f'{m:g}' for m in self.probe_m)} m along each axis) "
                              "found no contacts; set probe_m so that it reaches something")

    # ------------------------------------------------------------------ 4. following
    def _legs(self, runner, server, legs):
        """Per leg: (displacement, at the proxy after the hold, blocked, detail, back at start, detail)."""
        out = []
        leg = self._leg_s()
        for k, d in enumerate(legs):
            t_hold = k * leg + self.probe_ramp_s + self.probe_hold_s
            t_back = (k + 1) * leg
            target = server.start_pose.copy()
            target[:3] += d
            u = self._last_before(server, t_hold)
            ok, detail = self._at(u, target, server.start_joints)
            ub = self._last_before(server, t_back)
            back_ok, back_detail = self._at(ub, server.start_pose, server.start_joints)
            out.append((d, ok, u.n_contacts > 0, detail, back_ok or ub.n_contacts > 0, back_detail))
        return out

    def test_the_tool_follows_a_driven_proxy(self, subject):
        for scene in subject.scenes:
            runner, server, probe = self._probe(subject, scene)
            legs = self._legs(runner, server, probe)
            for d, ok, blocked, detail, back_ok, back_detail in legs:
                assert ok or blocked, f"{scene}: proxy moved by {d} m: the tool is {detail} away, and no contact"
                assert back_ok, f"{scene}: back at the start pose after {d}: the tool is {back_detail} away"
            assert any(ok for _, ok, *_ in legs), f"{scene}: the tool followed the proxy along no axis"

    # ------------------------------------------------------------------ 5. holding
    def test_holds_the_tool_while_the_proxy_is_not_rendered(self, subject):
        for scene in subject.scenes:
            runner, server, probe = self._probe(subject, scene)
            legs = self._legs(runner, server, probe)
            free = [d for d, ok, blocked, *_ in legs if ok and not blocked] or [d for d, ok, *_ in legs if ok]
            assert free, f"{scene}: no axis to test holding along (the tool followed none)"
            amp = min(0.06, 0.6 * float(np.linalg.norm(free[0])))
            d = free[0] / np.linalg.norm(free[0])
            speed = 0.1

            def script(t, s, d=d):
                pose = s.start_pose.copy()
                pose[:3] += d * min(amp, speed * max(0.0, t - 0.3))
                twist = np.zeros(6)
                if 0.3 <= t < 0.3 + amp / speed:
                    twist[:3] = d * speed
                state = ServerState.FAULT if 0.5 <= t < 1.2 else ServerState.ENGAGED
                return ProxyCommand(pose, twist, joint_position=s.start_joints,
                                    joint_velocity=np.zeros(len(s.start_joints)), server_state=state)

            runner2, server2 = simulate(subject.make(), scene, script, 2.2, config=self._config(),
                                        epsilon_m=self.epsilon_m)
            st = runner2.stats()
            assert st["proxy_held"] > 0 and st["holds"] == 1, f"{scene}: {st['proxy_held']} held, {st['holds']} holds"
            a = np.asarray(self._last_before(server2, 0.6).tool_pose[:3])
            b = np.asarray(self._last_before(server2, 1.2).tool_pose[:3])
            assert np.linalg.norm(b - a) <= 0.001, (
                f"{scene}: held (FAULT) from 0.5 s, the tool moved {np.linalg.norm(b - a) * 1e3:.2f} mm from 0.6 to 1.2 s")
            target = server2.start_pose.copy()
            target[:3] += d * amp
            ok, detail = self._at(self._last_before(server2, 2.2), target, server2.start_joints)
            assert ok, f"{scene}: engaged again from 1.2 s, the tool is {detail} from the proxy at 2.2 s"

    # ------------------------------------------------------------------ 6. determinism
    def test_is_deterministic_when_it_says_so(self, subject):
        if not getattr(subject.cls, "deterministic", False):
            pytest.skip(f"{subject.name} does not claim determinism (Engine.deterministic)")
        fields = ("env_time_s", "tool_pose", "keys", "position_m", "normal", "separation_m", "v_constr_m_per_s")
        for scene in subject.scenes:
            _, first, _ = self._probe(subject, scene)
            # a fresh engine through the first legs (each engine axis, both ways, the near distance)
            _, again, _ = self._probe(subject, scene, fresh=True, legs_run=6)
            assert len(again.updates) > 1 and len(first.updates) >= len(again.updates), scene
            again_until = again.updates[-1][0]
            prefix = [x for x in first.updates if x[0] <= again_until]
            assert len(prefix) == len(again.updates), f"{scene}: a different number of steps"
            for (ta, a), (tb, b) in zip(prefix, again.updates):
                assert ta == tb, f"{scene}: update times differ ({ta} vs {tb})"
                for name in fields:
                    va, vb = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
                    assert va.shape == vb.shape and np.array_equal(va, vb), f"{scene} at {ta:.3f} s: {name} differs"
