"""Each environment client against the real server (supervisor + loop process) over UDP and
Zenoh: handshake, updates both ways, the peg settling on the wall with the force balancing the
push, epsilon-contacts entering the model before contact, reconnection after a server restart,
and a client that survives a server that vanishes. Counts, positions and the engine's simulated
time, never timings (a wait for a count gives up after a generous bound only)."""
from __future__ import annotations

import os
import signal
import socket
import time

import numpy as np
import pytest

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


#: the planar device pushed towards the bottom wall (damping 10 N s/m: the hand reaches the wall
#: at about 0.1 m/s, under epsilon per engine step)
PLANAR_PUSH = {"kind": "planar", "damping_n_s_per_m": 10.0, "workspace_min_m": [-0.25, -0.25],
               "workspace_max_m": [0.25, 0.25], "hand": {"type": "constant", "wrench": [0.0, PUSH_N, 0.0]}}
#: the 6-DOF device pushed down
SPATIAL_PUSH = {"kind": "spatial", "damping_n_s_per_m": 10.0,
                "hand": {"type": "constant", "wrench": [0.0, 0.0, -PUSH_N, 0.0, 0.0, 0.0]}}


def _settings(url: str, device: dict = PLANAR_PUSH, ring_s: float = 20.0) -> cfgmod.Settings:
    return cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": url, "silence_timeout_s": 0.5},
        "status": {"address": f"127.0.0.1:{_port()}"},
        "model": {"epsilon_m": 0.005},
        "device": {"driver": "sim", "watchdog_s": 0.5, **device},
        "telemetry": {"ring_s": ring_s},
    })


def _engine(name: str):
    if name == "pymunk":
        from hapticproxy.clients.pymunk_engine import PymunkEngine

        return PymunkEngine()
    from hapticproxy.clients.stub_engine import StubEngine

    return StubEngine(seed=3)


#: generous bound of a wait for a count [s]: a cold numba cache costs the loop a minute first
_WAIT_S = 180.0


def _serve_until(sup: Supervisor, done, what: str) -> None:
    """Serve the status socket until ``done()``; fail naming ``what`` after ``_WAIT_S``."""
    t0 = time.monotonic()
    while not done():
        if time.monotonic() - t0 > _WAIT_S:
            raise AssertionError(f"gave up waiting for {what}")
        sup._serve_status(0.05)


@pytest.mark.parametrize("engine,transport", [("stub", "zenoh"), ("pymunk", "udp"),
                                              pytest.param("stub", "udp", marks=pytest.mark.slow),
                                              pytest.param("pymunk", "zenoh", marks=pytest.mark.slow)])
def test_client_against_the_real_server(engine, transport, real_session):
    snap, rows, stats, last = real_session(_settings(_url(transport)), _engine(engine), "testbed", 3.5)
    # the server's advice (protocol 1.2) reaches the client: an epsilon between the floor and the
    # grant, a bounded lead; at rest on the wall the advised epsilon is the floor
    assert 0.002 - 1e-12 <= last.epsilon_m <= stats["granted_epsilon_m"]
    assert snap["advised_epsilon_m"] == pytest.approx(0.002)
    assert abs(stats["epsilon_m"] - last.epsilon_m) <= 0.0005  # followed (re-inflated on changes above 0.5 mm)
    assert 0.0 <= last.lead_s <= 0.1 and stats["lead_s"] == pytest.approx(last.lead_s)
    # handshake and updates both ways
    assert stats["sessions"] == 1
    assert snap["updates"] >= 50 and stats["updates_sent"] >= snap["updates"]
    # every applied update acknowledged: the last perhaps in the step after the snapshot
    assert 0 <= snap["updates"] - snap["acks_sent"] <= 1
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
    return _settings(url, {"kind": "spatial"}, ring_s=5.0) if engine == "pybullet" else _settings(url)


# Reconnecting is the runner's and the transport's business, not the engine's: every transport
# and every engine once in the default run, the rest of the matrix with -m slow.
_DEFAULT_PAIRS = {("stub", "udp"), ("pymunk", "zenoh"), ("pybullet", "udp")}
_RECONNECT_MATRIX = [(e, t) if (e, t) in _DEFAULT_PAIRS else pytest.param(e, t, marks=pytest.mark.slow)
                     for e in ("stub", "pymunk", "pybullet") for t in ("udp", "zenoh")]


def _engaged_client(sup, engine, url, client_thread):
    """Start ``sup`` and a reconnecting client of ``engine``; serve until 20 updates arrived.
    Returns the client (closed by ``client_thread`` at the end if the wait fails) and its
    session count then."""
    sup.start()
    eng, scene = _any_engine(engine)
    client = client_thread(eng, url, scene=scene, connect_timeout_s=_WAIT_S, reconnect_delay_s=0.3).start()
    _serve_until(sup, lambda: sup.shared.snapshot()["updates"] >= 20, "20 updates")
    return client, client.runner.stats()["sessions"]


@pytest.mark.parametrize("engine,transport", _RECONNECT_MATRIX)
def test_reconnects_after_a_server_restart(engine, transport, client_thread):
    url = _url(transport)
    s = _settings_for(engine, url)
    sup = Supervisor(s)
    client = None
    try:
        client, first_sessions = _engaged_client(sup, engine, url, client_thread)
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


@pytest.mark.parametrize("engine,transport", _RECONNECT_MATRIX)
def test_client_survives_a_server_that_vanishes(engine, transport, client_thread):
    url = _url(transport)
    sup = Supervisor(_settings_for(engine, url))
    client = None
    try:
        client, first_sessions = _engaged_client(sup, engine, url, client_thread)
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
def test_pybullet_client_against_the_real_server(transport, real_session):
    """The 3-D client: a 40 mm cube 3 mm above the floor of the `loose` scene, pushed down with 0.5 N
    by the hand on a simulated 6-DOF device."""
    from hapticproxy.clients.pybullet_engine import PybulletEngine

    snap, rows, stats, _ = real_session(_settings(_url(transport), SPATIAL_PUSH), PybulletEngine(), "loose", 4.0)
    assert stats["sessions"] == 1 and snap["updates"] >= 50 and 0 <= snap["updates"] - snap["acks_sent"] <= 1
    assert snap["faults_total"] == 0, (snap["fault"], snap["device_fault"], snap["speed_trips"])
    eng = rows[rows[:, TEL["updates"]] > 0]
    last = eng[-300:]
    assert abs(np.mean(last[:, TEL["proxy_z"]]) - 0.020) < 0.002  # the cube rests on the floor
    assert abs(np.mean(last[:, TEL["cmd_fz"]]) - PUSH_N) < 0.05  # the floor pushes back the 0.5 N
    first = np.argmax(eng[:, TEL["contacts"]] > 0)
    assert eng[first, TEL["contacts"]] > 0 and eng[first, TEL["proxy_z"]] > 0.020  # predicted: still apart
