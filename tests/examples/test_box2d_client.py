"""The Box2D client written from SPEC.md alone (clients/examples/box2d_client.py), run as a user
runs it (``python clients/examples/box2d_client.py --connect URL``): it passes
``hapticproxy protocol check-client``, and against the real server (supervisor + loop process,
UDP loopback) a hand pushing the box down onto the floor rests it on the floor's surface with
the force balancing the push. It is an example, not part of the package: nothing imports it.
Positions and counts, never timings."""
from __future__ import annotations

import ast
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("Box2D")

from hapticproxy.protocol import conformance as K  # noqa: E402
from hapticproxy.protocol.transport import open_transport  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
CLIENT = ROOT / "clients" / "examples" / "box2d_client.py"
PUSH_N = 0.5
#: the box's half height and the floor's surface (y = 0), SPEC units [m]
BOX_HALF_HEIGHT_M = 0.015
STIFFNESS_N_PER_M = 4000.0  # the server's default contact stiffness


def _port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(url: str, seconds: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(CLIENT), "--connect", url, "--duration", str(seconds)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _stop(proc: subprocess.Popen) -> str:
    proc.terminate()
    _, err = proc.communicate(timeout=30)
    return err


def test_the_example_is_not_part_of_the_package():
    assert not (CLIENT.parent / "__init__.py").exists()
    tree = ast.parse(CLIENT.read_text())
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert "hapticproxy" not in imported  # written from SPEC.md alone, on msgpack and sockets
    for folder in ("protocol", "server", "clients", "cli", "benchmarks", "experiments"):
        for path in (ROOT / folder).rglob("*.py"):
            if "examples" not in path.parts:
                assert "box2d_client" not in path.read_text(errors="ignore"), path


def test_box2d_client_passes_check_client():
    listen = open_transport("udp://127.0.0.1:0", role="server")
    proc = _start(listen.url, 60)
    try:
        rep = K.check_client(listen, duration_s=0.5, timeout_s=60.0)
    finally:
        err = _stop(proc)
        listen.close()
    assert rep.passed, "\n".join(rep.lines()) + "\n" + err
    assert "Traceback" not in err


def _rows(sup) -> np.ndarray:
    head = int(sup.shared.head[0])
    n = min(head, sup.ring_rows)
    return sup.shared.ring[np.arange(head - n, head) % sup.ring_rows].copy()


def test_box2d_client_against_the_real_server_rests_on_the_floor_and_balances_the_push():
    from hapticproxy.server import config as cfgmod
    from hapticproxy.server.daemon import Supervisor
    from hapticproxy.server.shm import TEL

    url = f"udp://127.0.0.1:{_port()}"
    settings = cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": url, "silence_timeout_s": 0.5},
        "status": {"address": f"127.0.0.1:{_port()}"},
        "model": {"epsilon_m": 0.005, "stiffness_n_per_m": STIFFNESS_N_PER_M},
        "device": {"driver": "sim", "kind": "planar", "damping_n_s_per_m": 10.0, "watchdog_s": 0.5,
                   "workspace_min_m": [-0.25, -0.25], "workspace_max_m": [0.25, 0.25],
                   "hand": {"type": "constant", "wrench": [0.0, -PUSH_N, 0.0]}},  # pushes the box down
        "telemetry": {"ring_s": 30.0},
    })
    sup = Supervisor(settings)
    proc = None
    err = ""
    try:
        sup.start()
        proc = _start(url, 60)
        t0 = time.monotonic()
        # wait for 3 s of engagement, counted in updates the server applied (60 Hz)
        while time.monotonic() - t0 < 60 and sup.shared.snapshot()["updates"] < 180:
            sup._serve_status(0.05)
        snap = sup.shared.snapshot()
        rows = _rows(sup)
    finally:
        if proc is not None:
            err = _stop(proc)
        sup.close()
    assert snap["updates"] >= 180, err
    assert snap["faults_total"] == 0, (snap["fault"], snap["device_fault"])
    # every applied update acknowledged: the last perhaps in the step after the snapshot
    assert 0 <= snap["updates"] - snap["acks_sent"] <= 1
    eng = rows[rows[:, TEL["updates"]] > 0]
    assert np.max(eng[:, TEL["contacts"]]) >= 2  # the box's two bottom corners on the floor
    last = eng[-500:]  # the last 0.5 s
    assert np.all(last[:, TEL["contacts"]] == 2)
    # at rest: the box's bottom on the floor's surface, pressed in by the push shared by its
    # two corner contacts (0.25 N / 4000 N/m = 0.06 mm), nowhere else
    bottom = last[:, TEL["proxy_y"]] - BOX_HALF_HEIGHT_M
    expected = -PUSH_N / (2 * STIFFNESS_N_PER_M)
    assert np.all(np.abs(bottom - expected) < 0.2e-3), (bottom.min(), bottom.max(), expected)
    assert np.ptp(last[:, TEL["dev_y"]]) < 1e-4
    # the force on the hand balances its push: +0.5 N up against the 0.5 N down
    assert abs(np.mean(last[:, TEL["cmd_fy"]]) - PUSH_N) < 0.02
    assert abs(np.mean(last[:, TEL["cmd_fx"]])) < 0.02
    # epsilon-active: the floor was in the model before the box touched it (it starts 2 mm above)
    first = int(np.argmax(eng[:, TEL["contacts"]] > 0))
    assert eng[first, TEL["proxy_y"]] - BOX_HALF_HEIGHT_M > 0.0
    assert "Traceback" not in err
