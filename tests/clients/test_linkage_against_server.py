"""Linkage clients against the real server (supervisor + loop process) over UDP: the pymunk
testbed's 3-bar linkage pushed onto the bottom wall settles with the force balancing the push;
the pybullet URDF chain engages a spatial device. Counts, positions and the engine's simulated
time, never timings."""
from __future__ import annotations

import socket

import numpy as np
import pytest

from hapticproxy.clients.scenes import BOTTOM_WALL_Y_M, LINK_WIDTH_M
from hapticproxy.server import config as cfgmod
from hapticproxy.server.shm import TEL

PUSH_N = 0.5


def _port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _settings(url: str, device: dict) -> cfgmod.Settings:
    return cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": url, "silence_timeout_s": 0.5},
        "status": {"address": f"127.0.0.1:{_port()}"},
        # the links are light (their corners see 50-90 g of the chain): explicit contact damping
        # needs dt < 2 m / b, so 10 N s/m rather than the peg's 30; friction keeps the pressed
        # chain from splaying (the pivot under the push would buckle on a frictionless wall)
        "model": {"tool": "linkage", "epsilon_m": 0.005, "damping_n_s_per_m": 10.0, "mu_static": 0.5,
                  "mu_kinetic": 0.4},
        "device": {"driver": "sim", "watchdog_s": 0.5, **device},
        "telemetry": {"ring_s": 20.0},
    })


def test_pymunk_linkage_against_the_real_server_settles_on_the_wall(real_session):
    from hapticproxy.clients.pymunk_engine import PymunkEngine

    url = f"udp://127.0.0.1:{_port()}"
    settings = _settings(url, {"kind": "planar", "damping_n_s_per_m": 10.0, "workspace_min_m": [-0.25, -0.25],
                               "workspace_max_m": [0.25, 0.25],
                               "hand": {"type": "constant", "wrench": [0.0, PUSH_N, 0.0]}})
    snap, rows, stats, last = real_session(settings, PymunkEngine(), "linkage", 5.0, max_contacts=32)
    # every applied update acknowledged: the last perhaps in the step after the snapshot
    assert stats["sessions"] == 1 and snap["updates"] >= 100 and 0 <= snap["updates"] - snap["acks_sent"] <= 1
    assert snap["faults_total"] == 0, (snap["fault"], snap["device_fault"], snap["speed_trips"])
    assert len(last.joint_position) == 2 and len(last.joint_effort) == 2
    eng = rows[rows[:, TEL["updates"]] > 0]
    tail = eng[-300:]
    # the held link rests on the bottom wall (its frame origin half a link width above it) and
    # the device feels the push balanced
    assert abs(np.mean(tail[:, TEL["proxy_y"]]) - (BOTTOM_WALL_Y_M - LINK_WIDTH_M / 2)) < 0.003
    assert abs(np.mean(tail[:, TEL["cmd_fy"]]) + PUSH_N) < 0.05
    assert np.ptp(tail[:, TEL["dev_y"]]) < 1e-3
    assert np.max(eng[:, TEL["contacts"]]) >= 4


def test_pybullet_linkage_against_the_real_server_engages_a_spatial_device(real_session):
    pytest.importorskip("pybullet")
    from hapticproxy.clients.pybullet_linkage import PybulletLinkageEngine

    url = f"udp://127.0.0.1:{_port()}"
    settings = _settings(url, {"kind": "spatial", "hand": {"type": "constant", "wrench": [0.0, 0.0, -0.3, 0.0, 0.0, 0.0]}})
    snap, rows, stats, last = real_session(settings, PybulletLinkageEngine(), "chain", 3.0, max_contacts=32)
    assert stats["sessions"] == 1 and snap["updates"] >= 100 and 0 <= snap["updates"] - snap["acks_sent"] <= 1
    assert snap["faults_total"] == 0, (snap["fault"], snap["device_fault"], snap["speed_trips"])
    assert len(last.joint_position) == 3
    eng = rows[rows[:, TEL["updates"]] > 0]
    # pushed down onto the floor: contacts enter the model and the device feels them
    assert np.max(eng[:, TEL["contacts"]]) >= 4
    assert np.mean(eng[-300:, TEL["cmd_fz"]]) > 0.1
