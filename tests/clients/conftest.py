"""Shared helpers of the client tests: a reference server in a thread that records what it
accepted, a recording fake engine, and a runner in a thread. Everything binds 127.0.0.1 on free
ports and is stopped at the end of its test."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from hapticproxy.clients.engine import ContactBuffer, Engine, SceneInfo, ToolDescription
from hapticproxy.protocol.codec import Bye, Codec, ContactUpdate
from hapticproxy.protocol.conformance import run_reference_server
from hapticproxy.protocol.transport import open_transport
from hapticproxy.testing.cleanup import made_then_ended


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate, timeout_s: float = 10.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


class RecordingTransport:
    """Wraps a server transport for ``run_reference_server``: records every ContactUpdate the
    server is handed (decoded on the side, in arrival order)."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.codec = Codec()
        self.updates: list[ContactUpdate] = []
        self.byes = 0
        self.lock = threading.Lock()

    @property
    def url(self) -> str:
        return self.inner.url

    def send(self, data, peer=None):
        return self.inner.send(data, peer)

    def drain(self, *a, **kw):
        got = self.inner.drain(*a, **kw)
        for data, _ in got:
            msg = self.codec.try_decode(data)
            if isinstance(msg, ContactUpdate):
                with self.lock:
                    self.updates.append(msg)
            elif isinstance(msg, Bye):
                self.byes += 1
        return got

    def close(self) -> None:
        self.inner.close()


class ServerThread:
    """``run_reference_server`` on ``url`` in a thread; ``.updates`` lists the ContactUpdates it
    received. ``stop()`` ends it with Bye (the reference server's close_all)."""

    def __init__(self, url: str, **kw) -> None:
        self.transport = RecordingTransport(open_transport(url, role="server"))
        self.url = self.transport.url
        self.stop_event = threading.Event()
        self.endpoint = None

        def run():
            self.endpoint = run_reference_server(self.transport, self.stop_event, **kw)

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    @property
    def updates(self) -> list:
        with self.transport.lock:
            return list(self.transport.updates)

    def wait_for_bye(self, timeout_s: float = 10.0) -> None:
        """Wait until the client's Bye arrived: everything it sent before is in ``updates``."""
        wait_for(lambda: self.transport.byes > 0, timeout_s, "the client's Bye")

    def close(self) -> bool:
        """End the server (Bye); whether its thread stopped. For clean-up: never asserts."""
        if self.thread.is_alive() or not self.transport.inner.closed:
            self.stop_event.set()
            self.thread.join(10)
            self.transport.close()
        return not self.thread.is_alive()

    def stop(self) -> None:
        """End the server, in a test's body: its thread must stop."""
        assert self.close(), "reference server thread did not stop"

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class RunnerThread:
    """``runner.run(stop, **kw)`` in a thread; the exception it raised (if any) in ``.error``."""

    def __init__(self, runner, **kw) -> None:
        self.runner = runner
        self.stop_event = threading.Event()
        self.result = None
        self.error = None

        def run():
            try:
                self.result = runner.run(self.stop_event, **kw)
            except BaseException as exc:  # noqa: BLE001 - reported to the test
                self.error = exc

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    def join(self, timeout_s: float = 10.0) -> None:
        self.thread.join(timeout_s)
        assert not self.thread.is_alive(), "runner did not stop"

    def stop(self) -> None:
        self.stop_event.set()
        self.join()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


class ClientThread:
    """A ClientRunner for ``engine`` in a thread, against ``url``; ``close()`` stops it and closes
    the engine (the exception ``run`` raised, if any, in ``.error``)."""

    def __init__(self, engine, url, scene="testbed", **kw):
        from hapticproxy.clients.runner import ClientRunner

        kw.setdefault("epsilon_m", 0.005)
        kw.setdefault("max_contacts", 16)
        self.engine = engine
        self.runner = ClientRunner(engine, url, scene=scene, **kw)
        self.stop = threading.Event()
        self.error = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        try:
            self.runner.run(self.stop)
        except BaseException as exc:  # noqa: BLE001 - asserted by the test
            self.error = exc

    def start(self):
        self.thread.start()
        return self

    def close(self):
        self.stop.set()
        self.thread.join(15)
        self.engine.close()


class RecordingEngine(Engine):
    """A fake planar engine: fixed rate, ``n_contacts`` synthetic contacts against a floor (their
    separation follows the tool's y), records every ``drive_tool`` call."""

    name = "recording-engine"

    def __init__(self, rate_hz: float = 200.0, n_contacts: int = 3) -> None:
        self.rate_hz = rate_hz
        self.n_contacts = n_contacts
        self.driven: list[np.ndarray] = []
        self.steps = 0
        self.eps_history: list[float] = []
        self._t = 0.0
        self._y = 0.0
        self.lock = threading.Lock()

    @classmethod
    def scenes(cls):
        return ("floor",)

    def load_scene(self, name):
        if name not in self.scenes():
            raise ValueError(f"unknown scene {name!r}; choose one of: floor")
        return SceneInfo(name, ToolDescription("planar", 1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.01, 0.0, 0.0, 0.0)),
                         env_rate_hz=self.rate_hz)

    def set_epsilon(self, epsilon_m):
        self.eps_history.append(epsilon_m)

    def step(self, dt_s):
        self._t += dt_s
        self.steps += 1

    def drive_tool(self, proxy_pose, proxy_twist, wrench):
        with self.lock:
            self.driven.append(np.array(proxy_pose, dtype=float))
        self._y = float(proxy_pose[1])

    def tool_pose(self, out):
        out[:] = (0.0, self._y, 0.0, 1.0, 0.0, 0.0, 0.0)
        return out

    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        n = min(self.n_contacts, max_contacts)
        for i in range(n):
            buf.keys[i] = (0, 1, i)
            buf.position_m[i] = (0.01 * i, -0.05, 0.0)
            buf.normal[i] = (0.0, 1.0, 0.0)
            buf.separation_m[i] = self._y + 0.05 - 0.01
            buf.v_constr_m_per_s[i] = 0.0
        buf.n = n
        self.contacts_found = self.n_contacts
        return n

    @property
    def time_s(self):
        return self._t


LAB_MODULE = '''"""A lab's own engine, from its own package (a test fixture)."""
from hapticproxy.clients.stub_engine import StubEngine


class LabEngine(StubEngine):
    name = "lab-engine 0.1"
'''


def make_lab_package(root, entries=(("lab", "labengine:LabEngine"),)) -> None:
    """An installed third-party package in ``root`` (put it on sys.path): ``labengine.py`` and its
    ``.dist-info`` registering ``entries`` in the ``hapticproxy.engines`` group."""
    from pathlib import Path

    root = Path(root)
    (root / "labengine.py").write_text(LAB_MODULE)
    info = root / "labengine-0.1.dist-info"
    info.mkdir(exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: labengine\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[hapticproxy.engines]\n" + "".join(f"{n} = {t}\n" for n, t in entries))


@pytest.fixture
def make_lab():
    return make_lab_package


@pytest.fixture
def lab_package(tmp_path, monkeypatch):
    """The lab's package installed (on sys.path) for this test: engine ``lab``, and a second entry
    that tries to take the built-in name ``stub``."""
    make_lab_package(tmp_path, (("lab", "labengine:LabEngine"), ("stub", "labengine:LabEngine")))
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


@pytest.fixture
def make_pybullet():
    """Make PybulletEngines (DIRECT), a scene loaded and epsilon set when given; all closed at the
    end of the test."""
    pytest.importorskip("pybullet")
    from hapticproxy.clients.pybullet_engine import PybulletEngine

    made = []

    def make(scene: str | None = None, epsilon_m: float = 0.005, **kw):
        e = PybulletEngine(**kw)
        made.append(e)
        if scene is not None:
            e.load_scene(scene)
            e.set_epsilon(epsilon_m)
        return e

    yield make
    for e in made:
        e.close()


@pytest.fixture
def client_thread():
    """Make :class:`ClientThread` s; every one is closed at the end of the test."""
    yield from made_then_ended(ClientThread)


#: generous bound of a wait for a count [s] (a cold numba cache costs the server's loop a minute)
WAIT_S = 180.0


def serve_until(sup, done, what: str) -> None:
    """Serve a Supervisor's status socket until ``done()``; fail naming ``what`` after WAIT_S."""
    t0 = time.monotonic()
    while not done():
        if time.monotonic() - t0 > WAIT_S:
            raise AssertionError(f"gave up waiting for {what}")
        sup._serve_status(0.05)


@pytest.fixture
def real_session(client_thread):
    """``run(settings, engine, scene, sim_seconds, **runner kwargs)``: the real server (supervisor
    and loop process) with ``settings`` and a client of ``engine`` in ``scene``, served until the
    engine has run ``sim_seconds`` of its own (simulated) time; returns ``(status snapshot,
    telemetry rows, client stats, last ProxyState)`` after both stopped."""
    from hapticproxy.server.daemon import Supervisor

    def run(settings, engine, scene, sim_seconds, **kw):
        kw.setdefault("connect_timeout_s", WAIT_S)
        sup = Supervisor(settings)
        client = None
        try:
            sup.start()
            client = client_thread(engine, settings["transport"]["url"], scene, **kw).start()
            serve_until(sup, lambda: client.runner.stats()["env_time_s"] >= sim_seconds,
                        f"{sim_seconds} s of engine time")
            snap = sup.shared.snapshot()
            head = int(sup.shared.head[0])
            n = min(head, sup.ring_rows)
            rows = sup.shared.ring[np.arange(head - n, head) % sup.ring_rows].copy()
            stats = client.runner.stats()
            last = client.runner.last_proxy
        finally:
            if client is not None:
                client.close()
            sup.close()
        assert client.error is None, client.error
        return snap, rows, stats, last

    return run


@pytest.fixture
def server_thread():
    """Make :class:`ServerThread` s; every one is closed at the end of the test."""
    yield from made_then_ended(ServerThread)


def _end_runner(r: RunnerThread) -> None:
    r.stop_event.set()  # for clean-up: never asserts (RunnerThread.stop does)
    r.thread.join(10)


@pytest.fixture
def runner_thread():
    """Make :class:`RunnerThread` s; every one is stopped at the end of the test."""
    yield from made_then_ended(RunnerThread, _end_runner)


@pytest.fixture
def helpers():
    class H:
        pass

    h = H()
    h.free_udp_port = free_udp_port
    h.wait_for = wait_for
    h.RecordingEngine = RecordingEngine
    h.ServerThread = ServerThread
    return h
