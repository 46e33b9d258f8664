"""The device's buttons reach the engine, end to end (issue 30, section 3): the real server
(supervisor and loop process) with a simulated 6-DOF device whose hand presses button 0 on a
script, the pybullet client of the ``loose`` scene, which grasps the body its tool touches while
the button is held. The hand moves the tool against the loose box in front of it, presses the
button, lifts, lets go: the box rises with the tool and falls when released. Positions and
events on the engine's own (simulated) clock; no wall-clock bound in an assertion."""
from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from hapticproxy.server import config as cfgmod

pytest.importorskip("pybullet")

#: generous bound of a wait for a count [s] (a cold numba cache costs the server's loop a minute)
WAIT_S = 180.0


def serve_until(sup, done, what: str) -> None:
    """Serve the status socket until ``done()``; fail naming ``what`` after 2 ``WAIT_S``."""
    t0 = time.monotonic()
    while not done():
        assert time.monotonic() - t0 < 2 * WAIT_S, f"gave up waiting for {what}"
        sup._serve_status(0.05)


def _port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: the hand's target (device frame, from where the device rests): slowly towards +y, stopping
#: about 5 mm short of the loose box 35 mm ahead of the tool; button 0 held from 2.5 s to 5 s,
#: up 30 mm meanwhile
HAND = {"type": "impedance", "stiffness_n_per_m": 300.0, "damping_n_s_per_m": 5.0,
        "target": {"type": "waypoints", "points": [[0.0, [0, 0, 0, 0, 0, 0]], [2.0, [0, 0.03, 0, 0, 0, 0]],
                                                   [3.0, [0, 0.03, 0, 0, 0, 0]], [4.0, [0, 0.03, 0.03, 0, 0, 0]],
                                                   [6.0, [0, 0.03, 0.03, 0, 0, 0]]]},
        "buttons": [[0.0, 0], [2.5, 1], [5.0, 0]]}
#: the engine grasps what lies within this of its tool when the button is pressed [m]
REACH_M = 0.01


def test_a_button_on_the_device_grasps_and_lifts_a_box_in_the_scene(client_thread):
    from hapticproxy.clients.pybullet_engine import PybulletEngine
    from hapticproxy.server.daemon import Supervisor

    url = f"udp://127.0.0.1:{_port()}"
    settings = cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": url, "silence_timeout_s": 0.5},
        "status": {"address": f"127.0.0.1:{_port()}"},
        "model": {"epsilon_m": 0.005},
        "device": {"driver": "sim", "kind": "spatial", "watchdog_s": 0.5, "damping_n_s_per_m": 10.0,
                   "workspace_min_m": [-0.1, -0.1, -0.1], "workspace_max_m": [0.1, 0.1, 0.1], "hand": HAND},
        "telemetry": {"ring_s": 5.0},
    })
    eng = PybulletEngine(grasp_reach_m=REACH_M)
    box_z = []  # (engine time, the box's height, the body grasped) after every step
    orig_step = eng.step

    ids = {}

    def step(dt):
        orig_step(dt)
        ids.setdefault("box0", eng.scene_info.facts["body_ids"]["box0"])
        box_z.append((eng.time_s, float(eng.body_state(ids["box0"])[0][2]), eng.grasped))

    eng.step = step
    events = eng.grasp_events  # (kept: closing the engine drops its scene)
    sup = Supervisor(settings)
    client = None
    try:
        sup.start()
        client = client_thread(eng, url, "loose", connect_timeout_s=WAIT_S).start()
        # the engine's clock and the server's each run on their own: wait for the release, then
        # 1.5 s more of the engine's time (the box falls back)
        serve_until(sup, lambda: len(events) >= 2 and eng.time_s > events[1][0] + 1.5, "the grasp and release")
        snap = sup.shared.snapshot()
        last = client.runner.last_proxy
    finally:
        if client is not None:
            client.close()
        sup.close()
    assert client.error is None, client.error
    assert snap["faults_total"] == 0, (snap["fault"], snap["device_fault"])
    box0 = ids["box0"]
    kinds = [(k, b) for _, k, b in events]
    assert kinds[:2] == [("grasp", box0), ("release", box0)], events
    t_grasp, t_release = events[0][0], events[1][0]
    z = np.array([(t, zz) for t, zz, _ in box_z])
    before = z[z[:, 0] < t_grasp, 1]
    during = z[(z[:, 0] > t_grasp) & (z[:, 0] < t_release), 1]
    after = z[z[:, 0] > t_release + 1.0, 1]
    assert abs(before[-1] - 0.025) < 0.002                  # resting on the floor
    assert during.max() - 0.025 > 0.02                      # carried up with the tool (the hand lifts 30 mm)
    assert after.size and abs(after[-1] - 0.025) < 0.003    # let go: back on the floor
    assert last.device_inputs & 1 and last.buttons == 0      # the ProxyStates carried the button
