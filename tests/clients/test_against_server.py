"""Each environment client against the real server (supervisor + loop process) over UDP and
Zenoh: handshake, updates both ways, the peg settling on the wall with the force balancing the
push, epsilon-contacts entering the model before contact, reconnection after a server restart,
and a client that survives a server that vanishes. Counts, positions and the engine's simulated
time, never timings (a wait for a count gives up after a generous bound only)."""
from __future__ import annotations

import os
import signal
import socket
import threading
import time

import numpy as np
import pytest

from hapticproxy.clients.runner import ClientRunner
from hapticproxy.clients.scenes import WALL_CONTACT_Y_COM_M
from hapticproxy.server import config as cfgmod
from hapticproxy.server.daemon import Supervisor
from hapticproxy.server.shm import TEL

PUSH_N = 0.5


def _port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _url(transport: str) -> str:
    if transport == "udp":
        return f"udp://127.0.0.1:{_port()}"
    return f"zenoh://127.0.0.1:{_port(socket.SOCK_STREAM)}/t{os.getpid()}"


def _settings(url: str, **model) -> cfgmod.Settings:
    return cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": url, "silence_timeout_s": 0.5},
        "status": {"address": f"127.0.0.1:{_port()}"},
        "model": {"epsilon_m": 0.005, **model},
        # damping 10 N s/m: the hand reaches the wall at about 0.1 m/s, under epsilon per engine step
        "device": {"driver": "sim", "kind": "planar", "damping_n_s_per_m": 10.0, "watchdog_s": 0.5, "workspace_min_m": [-0.25, -0.25],
                   "workspace_max_m": [0.25, 0.25], "hand": {"type": "constant", "wrench": [0.0, PUSH_N, 0.0]}},
        "telemetry": {"ring_s": 20.0},
    })


def _engine(name: str):
    if name == "pymunk":
        from hapticproxy.clients.pymunk_engine import PymunkEngine

        return PymunkEngine()
    from hapticproxy.clients.stub_engine import StubEngine

    return StubEngine(seed=3)


class Client:
    def __init__(self, engine, url, scene="testbed", **kw):
        self.engine = engine
        self.runner = ClientRunner(engine, url, scene=scene, epsilon_m=0.005, max_contacts=16, **kw)
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


#: generous bound of a wait for a count [s]: a cold numba cache costs the loop a minute first
_WAIT_S = 180.0


def _serve_until(sup: Supervisor, done, what: str) -> None:
    """Serve the status socket until ``done()``; fail naming ``what`` after ``_WAIT_S``."""
    t0 = time.monotonic()
    while not done():
        if time.monotonic() - t0 > _WAIT_S:
            raise AssertionError(f"gave up waiting for {what}")
        sup._serve_status(0.05)


def _serve_for(sup: Supervisor, client, sim_seconds: float) -> None:
    """Serve until the client's engine has run ``sim_seconds`` of its own (simulated) time."""
    _serve_until(sup, lambda: client.runner.stats()["env_time_s"] >= sim_seconds,
                 f"{sim_seconds} s of engine time")


def _rows(sup: Supervisor) -> np.ndarray:
    head = int(sup.shared.head[0])
    n = min(head, sup.ring_rows)
    return sup.shared.ring[np.arange(head - n, head) % sup.ring_rows].copy()


@pytest.mark.parametrize("transport", ["udp", "zenoh"])
@pytest.mark.parametrize("engine", ["stub", "pymunk"])
def test_client_against_the_real_server(engine, transport):
    url = _url(transport)
    sup = Supervisor(_settings(url))
    client = None
    try:
        sup.start()
        client = Client(_engine(engine), url, connect_timeout_s=_WAIT_S).start()
        _serve_for(sup, client, 3.5)
        snap = sup.shared.snapshot()
        rows = _rows(sup)
        stats = client.runner.stats()
    finally:
        if client is not None:
            client.close()
        sup.close()
    assert client.error is None
    # handshake and updates both ways
    assert stats["sessions"] == 1
    assert snap["updates"] >= 50 and stats["updates_sent"] >= snap["updates"]
    assert snap["acks_sent"] == snap["updates"]
    assert stats["proxy_applied"] >= 0.5 * snap["acks_sent"]
    assert snap["faults_total"] == 0, (snap["fault"], snap["device_fault"], snap["speed_trips"])
    eng = rows[rows[:, TEL["updates"]] > 0]
    # the peg settles on the wall, the force balancing the push
    last = eng[-300:]
    assert abs(np.mean(last[:, TEL["proxy_y"]]) - WALL_CONTACT_Y_COM_M) < 0.003
    assert abs(np.mean(last[:, TEL["cmd_fy"]]) + PUSH_N) < 0.05
    assert np.ptp(last[:, TEL["dev_y"]]) < 1e-3
    # epsilon-active geometry: the wall is in the model before the proxy reaches it
    first = np.argmax(eng[:, TEL["contacts"]] > 0)
    assert eng[first, TEL["contacts"]] > 0
    assert eng[first, TEL["proxy_y"]] < WALL_CONTACT_Y_COM_M  # the proxy is still apart from the wall


def _any_engine(name):
    if name == "pybullet":
        from hapticproxy.clients.pybullet_engine import PybulletEngine

        return PybulletEngine(), "loose"
    return _engine(name), "testbed"


def _settings_for(engine: str, url: str) -> cfgmod.Settings:
    if engine != "pybullet":
        return _settings(url)
    return cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": url, "silence_timeout_s": 0.5},
        "status": {"address": f"127.0.0.1:{_port()}"},
        "device": {"driver": "sim", "kind": "spatial", "watchdog_s": 0.5},
        "telemetry": {"ring_s": 5.0},
    })


@pytest.mark.parametrize("transport", ["udp", "zenoh"])
@pytest.mark.parametrize("engine", ["stub", "pymunk", "pybullet"])
def test_reconnects_after_a_server_restart(engine, transport):
    url = _url(transport)
    s = _settings_for(engine, url)
    sup = Supervisor(s)
    client = None
    try:
        sup.start()
        eng, scene = _any_engine(engine)
        client = Client(eng, url, scene=scene, connect_timeout_s=_WAIT_S, reconnect_delay_s=0.3).start()
        _serve_until(sup, lambda: sup.shared.snapshot()["updates"] >= 20, "20 updates")
        first_sessions = client.runner.stats()["sessions"]
        sup.close()  # clean stop: forces ramp down, Bye to the client
        sup = Supervisor(s)  # same address
        sup.start()
        _serve_until(sup, lambda: sup.shared.snapshot()["updates"] >= 20, "20 updates to the restarted server")
        snap = sup.shared.snapshot()
        stats = client.runner.stats()
    finally:
        if client is not None:
            client.close()
        sup.close()
    assert client.error is None and first_sessions == 1
    assert stats["sessions"] == 2 and stats["sessions_ended"] >= 1
    assert snap["updates"] >= 20 and snap["faults_total"] == 0


@pytest.mark.parametrize("transport", ["udp", "zenoh"])
@pytest.mark.parametrize("engine", ["stub", "pymunk", "pybullet"])
def test_client_survives_a_server_that_vanishes(engine, transport):
    url = _url(transport)
    sup = Supervisor(_settings_for(engine, url))
    client = None
    try:
        sup.start()
        eng, scene = _any_engine(engine)
        client = Client(eng, url, scene=scene, connect_timeout_s=_WAIT_S, reconnect_delay_s=0.3).start()
        _serve_until(sup, lambda: sup.shared.snapshot()["updates"] >= 20, "20 updates")
        first_sessions = client.runner.stats()["sessions"]
        os.kill(int(sup.shared.snapshot()["pid"]), signal.SIGKILL)  # the loop process dies, no Bye
        sup.proc.join(10)
        # the client notices the silence and keeps trying
        t0 = time.monotonic()
        while client.runner.stats()["sessions_ended"] < 1 and time.monotonic() - t0 < _WAIT_S:
            time.sleep(0.05)
        stats = client.runner.stats()
        alive = client.thread.is_alive()
    finally:
        if client is not None:
            client.close()
        sup.close()
    assert first_sessions == 1
    assert alive and client.error is None
    assert stats["sessions_ended"] >= 1
    assert stats["state"] in ("connecting", "handshaking", "waiting")


@pytest.mark.parametrize("transport", ["udp", "zenoh"])
def test_pybullet_client_against_the_real_server(transport):
    """The 3-D client: a 40 mm cube 3 mm above the floor of the `loose` scene, pushed down with 0.5 N
    by the hand on a simulated 6-DOF device."""
    from hapticproxy.clients.pybullet_engine import PybulletEngine

    url = _url(transport)
    settings = cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": url, "silence_timeout_s": 0.5},
        "status": {"address": f"127.0.0.1:{_port()}"},
        "model": {"epsilon_m": 0.005},
        "device": {"driver": "sim", "kind": "spatial", "damping_n_s_per_m": 10.0, "watchdog_s": 0.5,
                   "hand": {"type": "constant", "wrench": [0.0, 0.0, -PUSH_N, 0.0, 0.0, 0.0]}},
        "telemetry": {"ring_s": 20.0},
    })
    sup = Supervisor(settings)
    client = None
    try:
        sup.start()
        client = Client(PybulletEngine(), url, scene="loose", connect_timeout_s=_WAIT_S).start()
        _serve_for(sup, client, 4.0)
        snap = sup.shared.snapshot()
        rows = _rows(sup)
        stats = client.runner.stats()
    finally:
        if client is not None:
            client.close()
        sup.close()
    assert client.error is None
    assert stats["sessions"] == 1 and snap["updates"] >= 50 and snap["acks_sent"] == snap["updates"]
    assert snap["faults_total"] == 0, (snap["fault"], snap["device_fault"], snap["speed_trips"])
    eng = rows[rows[:, TEL["updates"]] > 0]
    last = eng[-300:]
    assert abs(np.mean(last[:, TEL["proxy_z"]]) - 0.020) < 0.002  # the cube rests on the floor
    assert abs(np.mean(last[:, TEL["cmd_fz"]]) - PUSH_N) < 0.05  # the floor pushes back the 0.5 N
    first = np.argmax(eng[:, TEL["contacts"]] > 0)
    assert eng[first, TEL["contacts"]] > 0 and eng[first, TEL["proxy_z"]] > 0.020  # predicted: still apart
