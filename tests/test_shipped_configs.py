"""Every shipped scene config works with the client it names, as a new user runs them.

Each config in deploy/configs/ that names its client (a ``# client: ENGINE ARGS`` line) is served
by the real server (supervisor + loop process; its transport and status moved to free loopback
ports) and its client runs as the command a user types (``hapticproxy client ENGINE ARGS``, its
own process). Within a few seconds the simulated hand, whose script starts when the client
engages, has brought the tool into contact, and at rest the force on the device balances the
hand's push.
"""
from __future__ import annotations

import os
import re
import shlex
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hapticproxy.server import config as cfgmod

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p for p in (ROOT / "deploy" / "configs").glob("*.toml") if "# client:" in p.read_text())


def _port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _client_args(path: Path) -> list[str]:
    return shlex.split(re.search(r"^# client: (.+)$", path.read_text(), re.M).group(1))


#: a "-zenoh" config whose UDP twin is shipped too: the same scene over another transport
ZENOH_TWINS = {p.name: p.with_name(p.name.replace("-zenoh", "")) for p in CONFIGS
               if p.stem.endswith("-zenoh") and p.with_name(p.name.replace("-zenoh", "")) in CONFIGS}


def _without_transport_and_comments(path: Path) -> dict:
    data = cfgmod.load(path).data
    return {k: v for k, v in data.items() if k != "transport"}


@pytest.mark.parametrize("name", sorted(ZENOH_TWINS))
def test_a_zenoh_twin_is_its_udp_scene_over_zenoh(name):
    """Only the transport differs (so the twin's full run below is a slow extra: zenoh-peer.toml
    runs by default, and the transports have their own contract suite)."""
    zen = ROOT / "deploy" / "configs" / name
    udp = ZENOH_TWINS[name]
    assert _without_transport_and_comments(zen) == _without_transport_and_comments(udp)
    assert cfgmod.load(zen)["transport"]["url"].startswith("zenoh://")
    assert _client_args(zen) == _client_args(udp)
    assert f"--connect {cfgmod.load(zen)['transport']['url']}" in zen.read_text()  # its header says how to connect


def test_every_scene_family_and_transport_is_shipped():
    names = {p.name for p in CONFIGS}
    for need in ("udp-loopback.toml", "zenoh-peer.toml", "peg1d.toml", "peg1d-zenoh.toml",
                 "spatial-pybullet.toml", "spatial-pybullet-zenoh.toml", "linkage-planar.toml"):
        assert need in names
    kinds = {cfgmod.load(p)["device"]["kind"] for p in CONFIGS}
    assert kinds == {"1dof", "planar", "spatial"}


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.slow) if p.name in ZENOH_TWINS else p
                                  for p in CONFIGS], ids=lambda p: p.stem)
def test_shipped_config_makes_contact_with_its_client_and_balances_the_push(path):
    from hapticproxy.server.daemon import Supervisor
    from hapticproxy.server.shm import TEL

    base = cfgmod.load(path)
    url = base["transport"]["url"]
    if url.startswith("udp://"):
        url = f"udp://127.0.0.1:{_port()}"
    else:
        url = f"zenoh://127.0.0.1:{_port(socket.SOCK_STREAM)}/cfg{os.getpid()}"
    # not real-time (a CI box may refuse SCHED_FIFO); the device's own watchdog loosened like the
    # other real-server tests (a loaded box stalls a loop for 50 ms: it would recover, slower)
    settings = cfgmod.load(path, {"transport": {"url": url}, "status": {"address": f"127.0.0.1:{_port()}"},
                                  "loop": {"realtime": False}, "device": {"watchdog_s": 0.5},
                                  "telemetry": {"ring_s": 30.0}})
    hand = np.asarray(settings["device"]["hand"]["wrench"], dtype=float)
    push_n = float(np.linalg.norm(hand[:3] if len(hand) >= 3 else hand))
    sup = Supervisor(settings)
    client = None
    try:
        sup.start()
        client = subprocess.Popen([sys.executable, "-m", "hapticproxy.cli.main", "client", *_client_args(path),
                                   "--connect", url, "--connect-timeout", "60", "--quiet"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        t_end = time.monotonic() + 90.0
        while time.monotonic() < t_end and sup.shared.get("updates") == 0:
            sup._serve_status(0.05)
            assert client.poll() is None, client.stderr.read()
        t_end = time.monotonic() + 6.0
        while time.monotonic() < t_end:
            sup._serve_status(0.05)
        snap = sup.shared.snapshot()
        head = int(sup.shared.head[0])
        n = min(head, sup.ring_rows)
        rows = sup.shared.ring[np.arange(head - n, head) % sup.ring_rows].copy()
    finally:
        if client is not None:
            client.terminate()
            try:
                client.wait(15)
            except subprocess.TimeoutExpired:
                client.kill()
        sup.close()
    # no fault (a stall the loaded machine caused would have recovered by itself)
    assert snap["updates"] > 50 and snap["faults_total"] <= snap["stall_recoveries"], snap
    last = rows[-500:]
    assert np.all(last[:, TEL["contacts"]] > 0), f"{path.name}: no contact at the end"
    f = np.linalg.norm(last[:, [TEL["cmd_fx"], TEL["cmd_fy"], TEL["cmd_fz"]]], axis=1)
    assert abs(float(np.mean(f)) - push_n) < 0.05, f"{path.name}: {np.mean(f):.3f} N against a {push_n} N push"
