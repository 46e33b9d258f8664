"""The pybullet engine: scenes, epsilon-active contacts against analytic geometry and against
pybullet's own closest-point query, stable keys, constraint velocities, clustering, driving
without tunnelling or energy injection, determinism, and a session through the client runner.

Every test opens its own DIRECT physics client (``PybulletEngine``) and closes it."""
from __future__ import annotations

import math
import threading

import numpy as np
import pybullet as p
import pytest

from hapticproxy.clients.contacts import EDGE_EDGE, FACE_VERTEX, VERTEX_FACE, cluster_rows, split_feature
from hapticproxy.clients.engine import ContactBuffer
from hapticproxy.clients.geometry import quat_from_axis_angle as quat_axis_angle
from hapticproxy.clients.geometry import quat_to_matrix as rot
from hapticproxy.clients.narrowphase import _cluster
from hapticproxy.clients.pybullet_engine import PybulletEngine

EPS = 0.005
FREE_SPOT = (0.15, 0.15)  # over the peg scene's floor, far from the block
PEG_HALF = (0.010, 0.010, 0.030)
BLOCK_FACE_X = 0.05  # the block's +x outer face


@pytest.fixture
def make_engine(make_pybullet):
    return make_pybullet


def pose(x, y, z, q=(1.0, 0.0, 0.0, 0.0)):
    return np.array([x, y, z, *q], dtype=float)


def rows(buf: ContactBuffer) -> dict:
    """key tuple -> (position, normal, separation, v_constr) of the buffer's contacts."""
    n = buf.n
    return {tuple(int(v) for v in buf.keys[i]): (buf.position_m[i].copy(), buf.normal[i].copy(),
                                                 float(buf.separation_m[i]), float(buf.v_constr_m_per_s[i]))
            for i in range(n)}


def hold(e: PybulletEngine, target: np.ndarray, steps: int, buf: ContactBuffer | None = None, max_contacts=64):
    """Drive towards ``target`` for ``steps`` steps the way the runner does (contacts after each
    step); return the tool poses."""
    out = np.zeros((steps, 7))
    buf = buf or ContactBuffer(64)
    for k in range(steps):
        e.drive_tool(target, np.zeros(6), np.zeros(6))
        e.step(0.002)
        e.contacts(buf, max_contacts)
        e.tool_pose(out[k])
    return out


# ----------------------------------------------------------------------------------- scenes
@pytest.mark.parametrize("scene", PybulletEngine.scenes())
def test_scenes_load_with_a_spatial_tool_at_its_start_pose(make_engine, scene):
    e = make_engine()
    info = e.load_scene(scene)
    assert info.name == scene
    assert info.tool.kind == "spatial" and info.tool.mass_kg > 0
    assert all(v > 0 for v in info.tool.inertia_kg_m2[:3]) and info.tool.inertia_kg_m2[3:] == (0.0, 0.0, 0.0)
    assert info.env_rate_hz == pytest.approx(500.0)
    assert e.name.startswith("pybullet 3.")
    ids = info.facts["body_ids"]
    assert ids["tool"] == e.tool_id and "floor" in ids
    np.testing.assert_allclose(e.tool_pose(np.zeros(7)), pose(*info.facts["tool_start_m"]), atol=1e-12)
    # the start pose is free of penetration: no contact below zero separation
    buf = ContactBuffer(64)
    e.set_epsilon(EPS)
    e.contacts(buf, 64)
    assert np.all(buf.separation_m[:buf.n] > 0)


def test_peg_scene_hole_fits_the_peg_with_the_stated_clearance(make_engine):
    e = make_engine("peg")
    f = e.scene_info.facts
    assert f["hole_side_m"] - f["peg_size_m"][0] == pytest.approx(2 * f["peg_clearance_per_side_m"])
    assert f["peg_clearance_per_side_m"] == pytest.approx(0.0005)
    # the peg centred in the hole, resting 1 mm above the floor: all four walls and the floor
    # are epsilon-active, every wall at the clearance, the floor at 1 mm
    e.reset_tool_pose(pose(0, 0, PEG_HALF[2] + 0.001))
    buf = ContactBuffer(64)
    e.contacts(buf, 64)
    ids = f["body_ids"]
    seps = {name: buf.separation_m[:buf.n][buf.keys[:buf.n, 1] == ids[name]] for name in ids if name != "tool"}
    for wall in ("wall_+x", "wall_-x", "wall_+y", "wall_-y"):
        assert seps[wall].min() == pytest.approx(0.0005, abs=1e-9)
    assert seps["floor"].min() == pytest.approx(0.001, abs=1e-9) and len(seps["floor"]) == 4


def test_unknown_scene_and_bad_input_raise_value_errors_naming_the_field(make_engine):
    e = make_engine()
    with pytest.raises(ValueError, match="peg.*loose"):
        e.load_scene("testbed")
    e.load_scene("peg")
    with pytest.raises(ValueError, match="epsilon_m"):
        e.set_epsilon(-0.001)
    with pytest.raises(ValueError, match="epsilon_m"):
        e.set_epsilon(float("nan"))
    assert e.epsilon_m == 0.0
    start = e.tool_pose(np.zeros(7)).copy()
    with pytest.raises(ValueError, match="proxy_pose"):
        e.drive_tool(np.array([0.0, 0, 0, 1, 0, 0]), np.zeros(6), np.zeros(6))
    with pytest.raises(ValueError, match="proxy_pose"):
        e.drive_tool(pose(float("inf"), 0, 0), np.zeros(6), np.zeros(6))
    with pytest.raises(ValueError, match="wrench"):
        e.drive_tool(pose(0.2, 0, 0.1), np.zeros(6), np.zeros(5))
    with pytest.raises(ValueError, match="max_contacts"):
        e.contacts(ContactBuffer(4), 5)
    with pytest.raises(ValueError, match="dt_s"):
        e.step(0.0)
    # the bad drive commands were not applied: the tool holds its start pose
    for _ in range(50):
        e.step(0.002)
    np.testing.assert_allclose(e.tool_pose(np.zeros(7)), start, atol=1e-6)
    with pytest.raises(ValueError, match="max_speed_m_per_s"):
        PybulletEngine(max_speed_m_per_s=0.0)


# --------------------------------------------------------------------- contact geometry
def test_epsilon_contacts_appear_before_touching_with_analytic_geometry(make_engine):
    e = make_engine("peg")
    floor = e.scene_info.facts["body_ids"]["floor"]
    buf = ContactBuffer(64)
    theta = 0.3
    q = quat_axis_angle((0, 0, 1), theta)
    # 6 mm above the floor: beyond epsilon, nothing
    e.reset_tool_pose(pose(*FREE_SPOT, PEG_HALF[2] + 0.006, q))
    assert e.contacts(buf, 64) == 0
    # 4 mm above: the four bottom corners as vertex-face contacts, before the real tool touches
    gap = 0.004
    e.reset_tool_pose(pose(*FREE_SPOT, PEG_HALF[2] + gap, q))
    assert e.contacts(buf, 64) == 4
    got = rows(buf)
    R = rot(q)
    expected = {}
    for i in range(4):  # bottom vertices: z bit clear
        local = np.array([(1 if i & 1 else -1) * PEG_HALF[0], (1 if i & 2 else -1) * PEG_HALF[1], 0.0])
        corner = np.array([*FREE_SPOT, 0.0]) + R @ local
        expected[i] = corner
    for key, (pos, nrm, sep, vc) in got.items():
        kind, tool_vertex, region = split_feature(key[2])
        assert key[0] == 0 and key[1] == floor
        assert kind == VERTEX_FACE and region == 5  # the floor box's +z face
        np.testing.assert_allclose(pos, expected[tool_vertex], atol=1e-12)
        np.testing.assert_allclose(nrm, (0, 0, 1), atol=1e-12)
        assert 0 < sep <= EPS and sep == pytest.approx(gap, abs=1e-12)
        assert vc == 0.0  # a static body
    assert sorted(split_feature(k[2])[1] for k in got) == [0, 1, 2, 3]


def test_tilted_tool_separations_follow_the_corner_heights(make_engine):
    e = make_engine("peg")
    a = 0.1  # rotation about +x: the -y corners go down
    q = quat_axis_angle((1, 0, 0), a)
    low = 0.002
    zc = low + PEG_HALF[1] * math.sin(a) + PEG_HALF[2] * math.cos(a)
    e.reset_tool_pose(pose(*FREE_SPOT, zc, q))
    buf = ContactBuffer(64)
    assert e.contacts(buf, 64) == 4
    for key, (pos, nrm, sep, _) in rows(buf).items():
        vertex = split_feature(key[2])[1]
        y_local = PEG_HALF[1] if vertex & 2 else -PEG_HALF[1]
        expected = low + (y_local + PEG_HALF[1]) * math.sin(a)
        assert sep == pytest.approx(expected, abs=1e-12)
        assert pos[2] == 0.0 and nrm[2] == 1.0


def test_smallest_separation_agrees_with_pybullet_closest_points(make_engine):
    """For random peg poses around the block, the smallest separation this engine reports equals
    the smallest of pybullet's getClosestPoints distances over the bodies, up to pybullet's corner
    rounding (collision margins: pybullet's distance is never smaller, and at most ~1.4 mm larger
    here). A missing edge-edge or face-vertex pair shows as a smaller pybullet distance. (Per body
    the two may differ: a vertex or edge where two boxes of the block meet is no contact here.)"""
    e = make_engine("peg", epsilon_m=0.02)
    ids = [v for k, v in e.scene_info.facts["body_ids"].items() if k != "tool"]
    rng = np.random.default_rng(3)
    buf = ContactBuffer(64)
    compared = 0
    for _ in range(400):
        q = rng.normal(size=4)
        centre = rng.uniform((-0.04, -0.04, 0.02), (0.04, 0.04, 0.09))
        e.reset_tool_pose(np.concatenate([centre, q / np.linalg.norm(q)]))
        e.contacts(buf, 64)
        dists = [c[8] for body in ids for c in p.getClosestPoints(e.tool_id, body, 0.02, physicsClientId=e.client_id)]
        if not dists or min(dists) <= 0 or e.contacts_found > 64:
            continue  # nothing near, or penetration (a vertex's depth is not the bodies' depth)
        assert buf.n > 0
        assert -1e-9 <= min(dists) - buf.separation_m[:buf.n].min() <= 1.5e-3
        compared += 1
    assert compared > 100


def test_keys_are_unique_and_stable_while_the_peg_rests_in_the_hole(make_engine):
    e = make_engine("peg")
    e.reset_tool_pose(pose(0, 0, PEG_HALF[2] + 0.0005))
    buf = ContactBuffer(64)
    target = pose(0, 0, PEG_HALF[2])  # pressing on the hole's bottom
    hold(e, target, 20, buf)
    first = set(rows(buf))
    assert len(first) == buf.n >= 20
    kinds = {split_feature(k[2])[0] for k in first}
    # peg corners on the walls and the floor, peg edges across the rim; the corners where two
    # walls of the hole meet are inside the block, not contacts
    assert kinds == {VERTEX_FACE, EDGE_EDGE}
    for _ in range(100):
        hold(e, target, 1, buf)
        keys = buf.keys[:buf.n]
        assert len({tuple(k) for k in keys}) == buf.n
        assert set(rows(buf)) == first


def test_constraint_velocity_is_the_normal_velocity_of_the_moving_body_point(make_engine):
    e = make_engine("loose")
    box = e.scene_info.facts["body_ids"]["box0"]  # a 50 mm cube at (0, 0.08, 0.025)
    # the tool's +y face 3 mm from the box's -y face
    e.reset_tool_pose(pose(0.0, 0.08 - 0.025 - 0.003 - 0.020, 0.026))
    v = np.array([0.01, -0.2, 0.03])
    w = np.array([0.5, -1.0, 2.0])
    p.resetBaseVelocity(box, v.tolist(), w.tolist(), physicsClientId=e.client_id)
    buf = ContactBuffer(64)
    e.contacts(buf, 64)
    com = e.body_state(box)[0]
    on_box = 0
    for key, (pos, nrm, sep, vc) in rows(buf).items():
        if key[1] != box:
            assert vc == 0.0
            continue
        on_box += 1
        assert vc == pytest.approx(float(nrm @ (v + np.cross(w, pos - com))), abs=1e-12)
        assert nrm[1] == pytest.approx(-1.0, abs=1e-9)  # from the box towards the tool
    assert on_box >= 4
    # the box face moves towards the tool at ~0.2 m/s
    assert max(buf.v_constr_m_per_s[:buf.n]) > 0.15


def test_a_sphere_is_one_contact_at_its_point_nearest_the_tool(make_engine):
    e = make_engine("loose")
    sphere = e.scene_info.facts["body_ids"]["sphere0"]  # r = 25 mm at (0.08, -0.05, 0.025)
    centre = e.body_state(sphere)[0]
    gap = 0.003
    e.reset_tool_pose(pose(centre[0] - 0.025 - gap - 0.020, centre[1], centre[2] + 0.001))
    buf = ContactBuffer(64)
    e.contacts(buf, 64)
    on_sphere = {k: v for k, v in rows(buf).items() if k[1] == sphere}
    assert len(on_sphere) == 1
    (key, (pos, nrm, sep, _)), = on_sphere.items()
    assert split_feature(key[2]) == (FACE_VERTEX, 1, 0)  # the tool's +x face, the sphere
    np.testing.assert_allclose(nrm, (-1, 0, 0), atol=1e-12)
    np.testing.assert_allclose(pos, centre + 0.025 * nrm, atol=1e-12)
    assert sep == pytest.approx(gap, abs=1e-12)


# ---------------------------------------------------------------------------- clustering
def test_clustering_caps_the_count_and_keeps_the_deepest_real_contacts(make_engine):
    e = make_engine("peg")
    # tilted in the hole: many contacts at different depths
    e.reset_tool_pose(pose(0.0003, -0.0002, PEG_HALF[2] + 0.001, quat_axis_angle((1, 1, 0), 0.01)))
    full = ContactBuffer(64)
    e.contacts(full, 64)
    everything = rows(full)
    assert full.n == e.contacts_found > 8
    for cap in (1, 4, 8):
        buf = ContactBuffer(cap)
        assert e.contacts(buf, cap) == cap == buf.n
        assert e.contacts_found == full.n
        got = rows(buf)
        assert len(got) == cap
        for key, (pos, nrm, sep, vc) in got.items():
            ref = everything[key]  # a real contact, unchanged
            np.testing.assert_array_equal(pos, ref[0])
            assert sep == ref[2]
        assert min(s for (_, _, s, _) in got.values()) == full.separation_m[:full.n].min()


def test_compiled_clustering_selects_what_the_shared_helper_selects():
    rng = np.random.default_rng(7)
    for n, cap in ((12, 5), (30, 16), (40, 1), (25, 24)):
        src = ContactBuffer(64)
        src.n = n
        src.keys[:n, 1] = 3
        src.keys[:n, 2] = rng.permutation(n)
        src.position_m[:n] = rng.normal(size=(n, 3)) * 0.02
        nr = rng.normal(size=(n, 3))
        src.normal[:n] = nr / np.linalg.norm(nr, axis=1)[:, None]
        src.separation_m[:n] = rng.normal(size=n) * 0.002
        raw_f = np.zeros((n, 8))
        raw_f[:, 0:3] = src.position_m[:n]
        raw_f[:, 3:6] = src.normal[:n]
        raw_f[:, 6] = src.separation_m[:n]
        raw_i = np.zeros((n, 2), dtype=np.int64)
        raw_i[:, 1] = src.keys[:n, 2]
        env_int = np.array([[3, 0, 0]], dtype=np.int64)
        keep = np.zeros(n, dtype=np.int64)
        _cluster(raw_f, raw_i, env_int, np.arange(n, dtype=np.int64), n, cap, 0.1, np.zeros(n),
                 np.zeros(3 * n, dtype=np.int64), keep)
        assert list(np.flatnonzero(keep)) == cluster_rows(src, cap, 0.1)


# ------------------------------------------------------------------------------- driving
def test_driving_converges_to_a_free_target_pose(make_engine):
    e = make_engine("peg")
    start = e.tool_pose(np.zeros(7)).copy()
    q = quat_axis_angle((0, 0, 1), 0.5)
    target = pose(start[0] + 0.04, start[1] - 0.03, start[2] + 0.02, q)
    out = hold(e, target, 400)
    np.testing.assert_allclose(out[-1][:3], target[:3], atol=1e-5)
    assert abs(float(out[-1][3:] @ target[3:])) == pytest.approx(1.0, abs=1e-8)
    # the speed bound: never more than max_speed * dt per step
    steps = np.linalg.norm(np.diff(out[:, :3], axis=0), axis=1)
    assert steps.max() <= e.max_speed_m_per_s * 0.002 * (1 + 1e-6)


@pytest.mark.parametrize("report_contacts", [True, False])
def test_driving_towards_a_pose_behind_a_wall_stops_at_the_wall(make_engine, report_contacts):
    e = make_engine("peg")
    z = PEG_HALF[2] + 0.0001  # standing on the floor, beside the block's +x face
    e.reset_tool_pose(pose(0.09, 0.0, z))
    target = pose(-0.09, 0.0, z)  # on the far side of the block
    buf = ContactBuffer(64)
    xs = []
    for _ in range(400):
        e.drive_tool(target, np.zeros(6), np.zeros(6))
        e.step(0.002)
        if report_contacts:  # as the runner does
            e.contacts(buf, 64)
        xs.append(e.tool_pose(np.zeros(7))[0])
    xs = np.array(xs)
    wall = BLOCK_FACE_X + PEG_HALF[0]  # the tool centre's x when touching the block
    # the drive's guard cuts the set-point at the wall's plane (step finds the contacts itself
    # when nobody asked for them): never into the wall by more than the solver's slop
    assert xs.min() >= wall - 2e-5
    assert xs[-1] == pytest.approx(wall, abs=2e-5)


def test_a_tool_held_in_contact_gains_no_energy(make_engine):
    e = make_engine("loose")
    ids = e.scene_info.facts["body_ids"]
    loose = [ids[k] for k in ("box0", "box1", "box2", "sphere0", "sphere1")]
    # resting on the floor against box0's -y face
    y_touch = 0.08 - 0.025 - 0.020
    e.reset_tool_pose(pose(0.0, y_touch, 0.020))
    buf = ContactBuffer(64)

    def run(target, steps):
        kinetic = []
        for _ in range(steps):
            e.drive_tool(target, np.zeros(6), np.zeros(6))
            e.step(0.002)
            e.contacts(buf, 16)
            kinetic.append(e.tool_kinetic_energy_j())
        return np.array(kinetic)

    # the proxy at rest where the tool is, but 2 mm into the (static) floor: nothing moves
    kinetic = run(pose(0.0, y_touch, 0.018), 500)
    assert kinetic.max() < 1e-6
    out = e.tool_pose(np.zeros(7))
    assert abs(out[2] - 0.020) < 1e-4 and abs(out[1] - y_touch) < 1e-4
    for body in loose:
        _, _, lin, ang = e.body_state(body)
        assert np.linalg.norm(lin) < 1e-3 and np.linalg.norm(ang) < 1e-2
    # the proxy 2 mm into the loose box: the tool moves 2 mm (at up to max_speed: the box slides
    # on), then everything comes to rest and stays there (no limit cycle, no creep)
    kinetic = run(pose(0.0, y_touch + 0.002, 0.018), 1000)
    assert kinetic[500:].max() < 1e-9
    assert e.tool_pose(np.zeros(7))[1] == pytest.approx(y_touch + 0.002, abs=1e-5)
    box = e.body_state(ids["box0"])
    assert np.linalg.norm(box[2]) < 1e-3 and box[0][1] > 0.08 + 0.002 - 1e-4


def test_the_tool_pushes_a_loose_box(make_engine):
    e = make_engine("loose")
    box = e.scene_info.facts["body_ids"]["box0"]
    start = e.tool_pose(np.zeros(7)).copy()
    hold(e, pose(0.0, 0.15, start[2]), 600)
    box_pos = e.body_state(box)[0]
    tool = e.tool_pose(np.zeros(7))
    assert box_pos[1] > 0.15  # pushed along +y from 0.08
    assert tool[1] == pytest.approx(0.15, abs=1e-3)
    assert box_pos[1] - tool[1] >= 0.045 - 1e-3  # the box is ahead of the tool, not passed through


def test_two_runs_are_identical(make_engine):
    def run():
        e = make_engine("loose")
        buf = ContactBuffer(8)
        trace = []
        start = e.tool_pose(np.zeros(7)).copy()
        for k in range(300):
            t = k * 0.002
            e.drive_tool(pose(0.01 * math.sin(5 * t), start[1] + 0.2 * t, start[2] - 0.002), np.zeros(6), np.zeros(6))
            e.step(0.002)
            n = e.contacts(buf, 8)
            trace.append((e.tool_pose(np.zeros(7)), buf.keys[:n].copy(), buf.position_m[:n].copy(),
                          buf.separation_m[:n].copy(), buf.v_constr_m_per_s[:n].copy()))
        return trace

    a, b = run(), run()
    assert any(len(t[1]) > 0 for t in a)
    for ta, tb in zip(a, b):
        for xa, xb in zip(ta, tb):
            np.testing.assert_array_equal(xa, xb)


# ------------------------------------------------------------------------------- runner
def test_a_session_through_the_client_runner_against_the_reference_server(make_engine):
    from hapticproxy.clients.runner import ClientRunner
    from hapticproxy.protocol.codec import Codec, ContactUpdate
    from hapticproxy.protocol.conformance import run_reference_server
    from hapticproxy.protocol.transport import open_transport

    server_transport = open_transport("udp://127.0.0.1:0", role="server")
    codec = Codec()
    seen: list[ContactUpdate] = []
    inner_drain = server_transport.drain

    def recording_drain(*a, **kw):
        got = inner_drain(*a, **kw)
        for data, _ in got:
            msg = codec.try_decode(data)
            if isinstance(msg, ContactUpdate):
                seen.append(msg)
        return got

    server_transport.drain = recording_drain
    stop = threading.Event()
    server = threading.Thread(target=run_reference_server, args=(server_transport, stop), daemon=True)
    server.start()
    try:
        engine = make_engine()
        # the reference server's proxy sits at the origin: the loose scene's tool is driven down
        # onto the floor (and stops there), so contacts exist
        runner = ClientRunner(engine, server_transport.url, scene="loose", epsilon_m=EPS, max_contacts=8,
                              realtime=False, reconnect=False, connect_timeout_s=10.0)
        stats = runner.run(max_steps=300, duration_s=30.0)
    finally:
        stop.set()
        server.join(10)
        server_transport.close()
    assert stats["error"] is None
    assert stats["steps"] == 300 and stats["updates_sent"] == 300
    assert stats["proxy_applied"] > 0 and stats["granted_max_contacts"] == 8
    assert len(seen) > 0 and max(u.n_contacts for u in seen) > 0
    assert all(u.n_contacts <= 8 for u in seen)
    assert engine.tool_pose(np.zeros(7))[2] == pytest.approx(0.020, abs=1e-4)  # on the floor
