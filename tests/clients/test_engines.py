"""The planar engines (stub and pymunk) against analytic geometry: epsilon contacts before real
contact, separations and normals, stable keys, clustering, no tunnelling, no energy injection,
constraint velocities, the testbed's dimensions, and the stub's determinism."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hapticproxy.clients.contacts import FACE_VERTEX, VERTEX_FACE, split_feature
from hapticproxy.clients.engine import ContactBuffer
from hapticproxy.clients.geometry import planar_angle, planar_pose
from hapticproxy.clients.pymunk_engine import PymunkEngine
from hapticproxy.clients.scenes import (SCENES, BOTTOM_WALL_Y_M, HOLE_BOTTOM_Y_M, HOLE_WIDTH_M, IN_HOLE_POSE, TOOL_LENGTH_M,
                                        TOOL_WIDTH_M, WALL_CONTACT_Y_COM_M)
from hapticproxy.clients.stub_engine import StubEngine

EPS = 0.005
ENGINES = {"stub": lambda: StubEngine(seed=4), "pymunk": lambda: PymunkEngine()}
ZERO6 = np.zeros(6)


def make(name: str, scene: str, eps: float = EPS):
    e = ENGINES[name]()
    e.load_scene(scene)
    e.set_epsilon(eps)
    return e


def drive(e, x, y, th=0.0):
    e.drive_tool(planar_pose(x, y, th, np.zeros(7)), ZERO6, ZERO6)


def step(e, buf=None, cap=64):
    e.step(e.next_step_s() or 1.0 / 60.0)
    if buf is not None:
        return e.contacts(buf, cap)
    return 0


def driven(name: str, scene: str, target, steps: int):
    """An engine in ``scene`` after ``steps`` steps of its tool driven towards ``target`` (x, y[, th])."""
    e = make(name, scene)
    drive(e, *target)
    for _ in range(steps):
        step(e)
    return e


def pose_xyt(e):
    p = e.tool_pose(np.zeros(7))
    return p[0], p[1], planar_angle(p)


def corners(x, y, th):
    c, s = math.cos(th), math.sin(th)
    a, b = TOOL_LENGTH_M / 2, TOOL_WIDTH_M / 2
    return [(x + c * lx - s * ly, y + s * lx + c * ly) for lx, ly in ((-a, -b), (a, -b), (a, b), (-a, b))]


def rows(buf):
    return [(tuple(buf.keys[i]), buf.position_m[i].copy(), buf.normal[i].copy(), float(buf.separation_m[i]),
             float(buf.v_constr_m_per_s[i])) for i in range(buf.n)]


@pytest.mark.parametrize("name", ENGINES)
def test_epsilon_contacts_appear_before_real_contact(name):
    """Approaching the wall slowly: the first report is a predicted contact, 0 < d <= epsilon, and
    the real tool is still apart from the wall at that step."""
    e = make(name, "wall")
    buf = ContactBuffer(16)
    for k in range(2000):
        drive(e, 0.0, 0.10 + 0.01 * e.time_s)  # the proxy creeps towards the wall at 10 mm/s
        n = step(e, buf)
        if n:
            break
    assert n > 0, "never reached the wall"
    x, y, th = pose_xyt(e)
    real_gap = BOTTOM_WALL_Y_M - max(cy for _, cy in corners(x, y, th))
    d = buf.separation_m[:n]
    assert np.all(d > 0) and np.all(d <= EPS + 1e-9)
    assert real_gap > 0 and min(d) == pytest.approx(real_gap, abs=1e-6)
    assert min(d) > EPS - 0.001  # found within one step's creep of the epsilon boundary


@pytest.mark.parametrize("name", ENGINES)
@pytest.mark.parametrize("target", [(0.0, 0.115, 0.0), (0.01, 0.11, 0.12), (0.0, 0.15, 0.0), (0.0, 0.15, -0.05)],
                         ids=["apart-flat", "apart-tilted", "pressed-flat", "pressed-tilted"])
def test_separation_and_normal_match_the_analytic_wall(name, target):
    """Every reported contact is a tool corner against the wall y = 134 mm: normal (0, -1) (from the
    wall towards the tool), c_p on the wall below the corner, d = wall - corner y (negative when
    pressed in); and every corner within epsilon is reported."""
    e = driven(name, "wall", target, 150)
    buf = ContactBuffer(16)
    n = e.contacts(buf, 16)
    cs = corners(*pose_xyt(e))
    expected = {i for i, (_, cy) in enumerate(cs) if BOTTOM_WALL_Y_M - cy <= EPS - 1e-5}
    maybe = {i for i, (_, cy) in enumerate(cs) if BOTTOM_WALL_Y_M - cy <= EPS + 1e-5}
    got = set()
    for key, cp, nrm, d, vc in rows(buf):
        kind, tool_feat, _ = split_feature(key[2])
        assert kind == VERTEX_FACE
        cx, cy = cs[tool_feat]
        assert nrm == pytest.approx([0.0, -1.0, 0.0], abs=1e-9)
        assert cp == pytest.approx([cx, BOTTOM_WALL_Y_M, 0.0], abs=1e-6)
        assert d == pytest.approx(BOTTOM_WALL_Y_M - cy, abs=1e-6)
        assert vc == 0.0
        got.add(tool_feat)
    assert expected <= got <= maybe
    if target[1] == 0.15:
        assert n > 0 and min(buf.separation_m[:n]) < 0  # pressed in: negative separation


@pytest.mark.parametrize("name", ENGINES)
def test_wall_is_met_at_the_papers_y_com(name):
    """Fig. 14: the unrotated peg pushed towards the bottom wall stops with its centre at 124 mm."""
    x, y, th = pose_xyt(driven(name, "wall", (0.0, 0.20), 240))
    assert WALL_CONTACT_Y_COM_M == pytest.approx(0.124)
    assert y == pytest.approx(0.124, abs=0.001) and abs(th) < 0.01


@pytest.mark.parametrize("name", ENGINES)
def test_peg_in_hole_touches_both_sides_and_bottom_with_stable_keys(name):
    e = driven(name, "hole", IN_HOLE_POSE, 30)
    buf = ContactBuffer(16)
    keysets = []
    for _ in range(30):
        n = step(e, buf)
        keys = [tuple(k) for k in buf.keys[:n]]
        assert len(set(keys)) == n  # unique within an update
        keysets.append(frozenset(keys))
    assert len(set(keysets)) == 1  # the same features touch: the same keys, step after step
    normals = {tuple(np.round(buf.normal[i, :2], 6)) for i in range(buf.n)}
    # every constraint is one of the hole's three faces, also where the peg's corners sit exactly on
    # the hole's bottom corners (a corner-corner normal from a rounding-sized gap would point anywhere)
    assert {(abs(a) and a, abs(b) and b) for a, b in normals} == {(1.0, 0.0), (-1.0, 0.0), (0.0, -1.0)}
    # exact fit: both side walls at zero separation, the bottom too
    assert np.all(np.abs(buf.separation_m[:buf.n]) < 2e-4)
    side = [r for r in rows(buf) if abs(r[2][0]) > 0.5]
    assert {round(r[1][0], 6) for r in side} == {round(-HOLE_WIDTH_M / 2, 6), round(HOLE_WIDTH_M / 2, 6)}
    mouth = [r for r in side if abs(r[1][1] - BOTTOM_WALL_Y_M) < 1e-6]
    assert len(mouth) == 2 and all(split_feature(r[0][2])[0] == FACE_VERTEX for r in mouth)  # corners on the peg's faces
    bottom = [r for r in rows(buf) if r[2][1] < -0.5]
    assert bottom and all(r[1][1] == pytest.approx(HOLE_BOTTOM_Y_M, abs=1e-6) for r in bottom)


@pytest.mark.parametrize("name", ENGINES)
def test_clustering_caps_the_count_and_keeps_the_deepest_of_each_direction(name):
    pressed = (IN_HOLE_POSE[0] + 0.002, IN_HOLE_POSE[1] + 0.01, IN_HOLE_POSE[2])  # into the bottom-right
    e = driven(name, "hole", pressed, 60)
    full, capped = ContactBuffer(64), ContactBuffer(3)
    n_full = e.contacts(full, 64)
    assert n_full > 3
    n = e.contacts(capped, 3)
    assert n == 3 and e.contacts_found == n_full
    keys_full = {tuple(k): i for i, k in enumerate(full.keys[:n_full])}
    kept = [tuple(k) for k in capped.keys[:n]]
    assert len(set(kept)) == 3 and set(kept) <= set(keys_full)  # real contacts, unique keys
    deepest = tuple(full.keys[int(np.argmin(full.separation_m[:n_full]))])
    assert deepest in kept
    # one representative per constraint direction (left wall, right wall, bottom)
    dirs = {tuple(np.round(capped.normal[i, :2]).astype(int)) for i in range(n)}
    assert dirs == {(1, 0), (-1, 0), (0, -1)}
    for k in kept:  # each representative is the deepest of its direction
        i = keys_full[k]
        same = [j for j in range(n_full) if np.dot(full.normal[j], full.normal[i]) > 0.99]
        assert full.separation_m[i] == min(full.separation_m[j] for j in same)


@pytest.mark.parametrize("name", ENGINES)
def test_no_tunnelling_when_the_proxy_jumps_deep_into_the_wall(name):
    e = make(name, "wall")
    drive(e, 0.0, 0.6)  # 0.47 m past the wall's face
    ys = []
    for _ in range(300):
        step(e)
        ys.append(max(cy for _, cy in corners(*pose_xyt(e))))
    assert max(ys) < BOTTOM_WALL_Y_M + 0.003  # pressed against it, never through


@pytest.mark.parametrize("name", ENGINES)
def test_no_tunnelling_through_the_testbed_shoulder(name):
    """The unrotated peg is too long for the hole: a proxy far below keeps it on the shoulders."""
    x, y, th = pose_xyt(driven(name, "testbed", (0.0, 0.5), 300))
    assert y < WALL_CONTACT_Y_COM_M + 0.003


def test_stub_coupling_does_not_inject_energy():
    """Free motion towards a still proxy: kinetic plus coupling energy never grows (implicit Euler)."""
    e = make("stub", "testbed")
    drive(e, 0.02, 0.01, 0.4)  # inside the linear range of the coupling spring
    kc, kr, m, iz = e._kc, e._kr, e.mass_kg, e.izz_kg_m2
    energies = []
    for _ in range(200):
        x, y, th = e._q
        vx, vy, w = e._v
        energies.append(0.5 * m * (vx * vx + vy * vy) + 0.5 * iz * w * w
                        + 0.5 * kc * ((0.02 - x) ** 2 + (0.01 - y) ** 2) + 0.5 * kr * (0.4 - th) ** 2)
        step(e)
    assert energies[0] > 0
    assert all(b <= a + 1e-15 * energies[0] for a, b in zip(energies, energies[1:]))  # up to rounding
    assert energies[-1] < 1e-6 * energies[0]


def test_pymunk_tool_speed_is_bounded_by_the_coupling():
    """A still proxy far away: the tool approaches no faster than the coupling's max_bias and comes
    to rest on the proxy (the constraint only removes the error, it adds no energy)."""
    e = make("pymunk", "testbed")
    drive(e, 0.1, 0.05, 0.0)
    speeds = []
    for _ in range(180):
        step(e)
        speeds.append(e.tool.velocity.length)
    assert max(speeds) <= e.max_speed_m_per_s * 1.01
    x, y, th = pose_xyt(e)
    assert (x, y) == pytest.approx((0.1, 0.05), abs=1e-4) and speeds[-1] < 1e-3


def test_stub_moving_wall_reports_its_normal_velocity():
    e = make("stub", "piston")
    buf = ContactBuffer(16)
    drive(e, 0.0, 0.125)
    seen = 0
    for _ in range(200):
        n = step(e, buf)
        t = e.time_s
        expect = 0.020 * 2 * math.pi * 0.5 * math.cos(2 * math.pi * 0.5 * t)  # n . v(c_p), towards the tool > 0
        wall_y = BOTTOM_WALL_Y_M - 0.020 * math.sin(2 * math.pi * 0.5 * t)
        for key, cp, nrm, d, vc in rows(buf):
            assert vc == pytest.approx(expect, abs=1e-12)
            assert cp[1] == pytest.approx(wall_y, abs=1e-12)
            seen += 1
    assert seen > 0


def test_pymunk_pushed_body_reports_its_constraint_velocity():
    e = make("pymunk", "push")
    buf = ContactBuffer(16)
    box_a = e.movable[0]
    box_a_id = 1 + [ob.name for ob in SCENES["push"].obstacles].index("box A")  # env body ids follow the scene
    drive(e, 0.0, 0.0)
    for _ in range(10):
        step(e)
    pushing = []
    for _ in range(40):
        drive(e, 0.0, 0.02 + 0.2 * e.time_s)  # push box A towards +y
        n = step(e, buf)
        for i in range(n):
            if buf.keys[i, 1] != box_a_id:
                continue
            v = box_a.velocity_at_world_point((buf.position_m[i, 0], buf.position_m[i, 1]))
            expect = buf.normal[i, 0] * v.x + buf.normal[i, 1] * v.y
            assert buf.v_constr_m_per_s[i] == pytest.approx(expect, abs=1e-12)
            pushing.append(buf.v_constr_m_per_s[i])
    assert pushing and min(pushing) < -0.01  # the box moves away from the tool: negative


def test_stub_is_deterministic_for_a_seed_and_its_rate_varies_within_30_to_60_hz():
    def run(seed):
        e = make("stub", "testbed")
        e.__init__(seed=seed)
        e.load_scene("testbed")
        e.set_epsilon(EPS)
        buf = ContactBuffer(16)
        out = []
        for k in range(300):
            drive(e, 0.02 * math.sin(0.05 * k), 0.05 + 0.1 * math.sin(0.02 * k), 0.3 * math.sin(0.03 * k))
            dt = e.next_step_s()
            e.step(dt)
            n = e.contacts(buf, 16)
            out.append((dt, tuple(e.tool_pose(np.zeros(7))), buf.keys[:n].tobytes(), buf.position_m[:n].tobytes(),
                        buf.normal[:n].tobytes(), buf.separation_m[:n].tobytes()))
        return out

    a, b, c = run(11), run(11), run(12)
    assert a == b
    assert [r[0] for r in a] != [r[0] for r in c]
    dts = np.array([r[0] for r in a])
    assert dts.min() >= 1 / 60 - 1e-12 and dts.max() <= 1 / 30 + 1e-12
    assert dts.std() > 0.001  # variable, with jitter
    assert any(r[2] for r in a)  # contacts happened on the way


@pytest.mark.parametrize("name", ENGINES)
def test_unknown_scene_names_the_choices(name):
    e = ENGINES[name]()
    with pytest.raises(ValueError, match="unknown scene 'moon'; choose one of: testbed"):
        e.load_scene("moon")


@pytest.mark.parametrize("name", ENGINES)
def test_negative_epsilon_is_refused(name):
    e = make(name, "wall")
    with pytest.raises(ValueError, match="epsilon_m"):
        e.set_epsilon(-0.001)


@pytest.mark.parametrize("name", ENGINES)
def test_scene_info_describes_the_papers_peg(name):
    e = ENGINES[name]()
    info = e.load_scene("testbed")
    assert info.tool.kind == "planar" and info.tool.mass_kg == 0.25
    assert info.tool.inertia_kg_m2[2] == pytest.approx(0.25 * (0.08 ** 2 + 0.02 ** 2) / 12)
    assert info.facts["wall_contact_y_com_m"] == pytest.approx(0.124)
    assert info.facts["hole_x_m"] == pytest.approx((-0.01, 0.01))
    assert 30.0 <= info.env_rate_hz <= 60.0
