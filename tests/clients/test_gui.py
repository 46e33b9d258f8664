"""The live windows, headless: what the pymunk window draws (pygame on SDL's dummy video driver,
pixels read back from its surface: the proxy's ghost, the force on the hand, the epsilon band,
the contacts, the server state; a fault visibly different), and what the pybullet GUI computes and
draws (its camera frames the scene, the ghost sits at the proxy in the state's colour, one normal
per contact), on a DIRECT physics client since no display is available here."""
from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from hapticproxy.clients.contract import ProxyCommand, ScriptedServer, SimClock
from hapticproxy.clients.geometry import planar_pose
from hapticproxy.clients.gui import (BANNER_PX, EPSILON_RGB, FORCE_PX_PER_N, FORCE_RGB, Viewport, inflated_outline,
                                     tool_outlines)
from hapticproxy.clients.runner import ClientRunner
from hapticproxy.clients.views import PREDICTED_RGB, PROXY_RGB, ViewState, state_style
from hapticproxy.protocol.messages import ServerState

EPS = 0.005


# ------------------------------------------------------------------------------ pure geometry
def test_the_epsilon_band_is_the_tool_swept_by_a_disc_of_radius_epsilon():
    square = [(-0.01, -0.01), (0.01, -0.01), (0.01, 0.01), (-0.01, 0.01)]
    band = inflated_outline(square, EPS, segments_per_corner=8)
    for x, y in band:  # every point at epsilon from the square (outside it)
        dx, dy = max(abs(x) - 0.01, 0.0), max(abs(y) - 0.01, 0.0)
        assert math.hypot(dx, dy) == pytest.approx(EPS, abs=1e-12)
    xs, ys = [x for x, _ in band], [y for _, y in band]
    assert (min(xs), max(xs), min(ys), max(ys)) == pytest.approx((-0.015, 0.015, -0.015, 0.015))
    assert inflated_outline(square, 0.0) == square


def test_state_styles_tell_the_states_apart():
    colours = {s: state_style(s)[1] for s in (ServerState.ENGAGED, ServerState.FADING, ServerState.FAULT,
                                              ServerState.IDLE)}
    assert len(set(colours.values())) == 4
    assert state_style(ServerState.FAULT)[0].startswith("FAULT") and state_style(None)[0] == "NO SESSION"
    assert state_style(ServerState.UNKNOWN)[1] == colours[ServerState.ENGAGED]  # a 1.1 server: engaged


# ------------------------------------------------------------------------------ pymunk window
@pytest.fixture
def window_engine(monkeypatch):
    pytest.importorskip("pygame")
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")
    from hapticproxy.clients.pymunk_engine import PymunkEngine

    engine = PymunkEngine(gui=True)
    yield engine
    engine.close()


def _view(state, *, proxy=(0.0, 0.05), force=(0.0, -0.5), following=True, contacts=True) -> ViewState:
    vs = ViewState(server_state=state, proxy_pose=planar_pose(proxy[0], proxy[1], 0.0, np.zeros(7)),
                   hand_wrench=np.array([force[0], force[1], 0.0, 0.0, 0.0, 0.0]),
                   tool_pose=planar_pose(0.0, 0.0, 0.0, np.zeros(7)), epsilon_m=EPS, following=following)
    if contacts:
        vs.contact_position_m = np.array([[0.1, 0.134, 0.0]])
        vs.contact_normal = np.array([[0.0, -1.0, 0.0]])
        vs.contact_separation_m = np.array([0.002])
    return vs


def _rgb(window, xy):
    c = window.screen.get_at((int(xy[0]), int(xy[1])))
    return (c.r, c.g, c.b)


def test_pymunk_window_draws_proxy_force_band_contacts_and_state(window_engine):
    e = window_engine
    e.load_scene("wall")
    w = e.window
    vp = Viewport()
    w.render(_view(ServerState.ENGAGED))
    width, height = w.screen.get_size()
    # the banner in the state's colour
    assert _rgb(w, (width - 4, BANNER_PX // 2)) == state_style(ServerState.ENGAGED)[1]
    # the ghost at the proxy (50 mm below the tool): blue, translucent over the white background
    gx, gy = vp.px(0.03, 0.05)
    r, g, b = _rgb(w, (gx, gy))
    assert b > r + 40 and (r, g, b) != (255, 255, 255) and (r, g, b) != PROXY_RGB
    assert _rgb(w, vp.px(0.03, 0.08)) == (255, 255, 255)  # nothing beyond it
    # the force on the hand: 0.5 N up (screen -y) from where the hand holds the proxy
    hx, hy = vp.px(0.0, 0.05)
    length = FORCE_PX_PER_N * 0.5
    assert _rgb(w, (hx, hy - 0.5 * length)) == FORCE_RGB
    assert _rgb(w, (hx, hy - length - 6)) != FORCE_RGB and _rgb(w, (hx, hy + 10)) != FORCE_RGB
    # the epsilon band: epsilon beyond the tool's right face, not between
    bx, by = vp.px(0.04 + EPS, 0.0)
    assert _rgb(w, (bx, by)) == EPSILON_RGB
    assert _rgb(w, (vp.px(0.04 + EPS / 2, 0.0)[0], by)) == (255, 255, 255)
    # a predicted contact: an orange dot at c_p
    assert _rgb(w, vp.px(0.1, 0.134)) == PREDICTED_RGB
    # no fault frame while engaged
    assert _rgb(w, (2, height // 2)) == (255, 255, 255)


def test_pymunk_window_shows_a_fault_and_a_held_proxy(window_engine):
    e = window_engine
    e.load_scene("wall")
    w = e.window
    vp = Viewport()
    width, height = w.screen.get_size()
    banners = {}
    for state in (ServerState.ENGAGED, ServerState.FADING, ServerState.FAULT, ServerState.IDLE, None):
        w.render(_view(state, following=state == ServerState.ENGAGED))
        banners[state] = _rgb(w, (width - 4, BANNER_PX // 2))
    assert len(set(banners.values())) == 4  # idle and no session share grey
    # the fault: a red frame round the whole window, and the ghost in the fault's colour
    w.render(_view(ServerState.FAULT, following=False))
    red = state_style(ServerState.FAULT)[1]
    assert _rgb(w, (2, height // 2)) == red and _rgb(w, (width - 3, height - 3)) == red
    r, g, b = _rgb(w, vp.px(0.03, 0.05))
    assert r > b + 40  # the held proxy's ghost is red, not blue
    # no force, no arrow
    w.render(_view(ServerState.ENGAGED, force=(0.0, 0.0)))
    hx, hy = vp.px(0.0, 0.05)
    assert _rgb(w, (hx, hy - 0.25 * FORCE_PX_PER_N)) != FORCE_RGB


def test_pymunk_window_draws_the_linkage_proxy_link_by_link(window_engine):
    e = window_engine
    e.load_scene("linkage")
    vs = _view(ServerState.ENGAGED, proxy=(-0.105, 0.06), force=(0.0, 0.0), contacts=False)
    vs.proxy_joint_position = np.array([0.0, math.pi / 2])  # the last link turned down (+y)
    e.window.render(vs)
    polys = tool_outlines(True, e._link_local, vs.proxy_pose, vs.proxy_joint_position)
    assert len(polys) == 3
    # the middle of the last link: straight down from the second joint at (0.035, 0.06)
    r, g, b = _rgb(e.window, Viewport().px(0.035, 0.06 + 0.035))
    assert b > r + 40


def test_the_window_follows_a_session_in_simulated_time(window_engine):
    """The runner updates the engine's window after its steps; once the server reports a fault,
    the window shows it."""
    e = window_engine
    clock = SimClock()

    def script(t, s):
        pose = s.start_pose.copy()
        pose[1] = 0.05 * min(t, 0.2)
        return ProxyCommand(pose, wrench=np.array([0.0, 0.4, 0.0, 0.0, 0.0, 0.0]),
                            server_state=ServerState.FAULT if t >= 0.3 else ServerState.ENGAGED)

    srv = ScriptedServer(clock, script)
    seen = {}

    def on_step(runner):
        state = runner.server_state
        if state not in seen and e.window.update(runner, force=True):
            w = e.window
            seen[state] = _rgb(w, (w.screen.get_size()[0] - 4, BANNER_PX // 2))

    runner = ClientRunner(e, srv.url, scene="wall", clock_ns=clock, sleep=srv.sleep, on_step=on_step)
    st = runner.run(duration_s=0.5)
    assert st["holds"] == 1
    assert seen["engaged"] == state_style(ServerState.ENGAGED)[1]
    assert seen["fault"] == state_style(ServerState.FAULT)[1]
    assert e.window.frames >= 2


# ------------------------------------------------------------------------------ pybullet GUI
@pytest.mark.parametrize("scene", ["peg", "loose"])
def test_the_camera_frames_the_scene(make_pybullet, scene):
    """Every corner of the scene's bodies (the floor aside) projects inside the view, and the
    scene fills a good part of it; pybullet's default camera (5 m away) showed a few pixels."""
    import pybullet as p

    from hapticproxy.clients.pybullet_gui import camera_matrices, frame_camera, project, scene_bounds

    e = make_pybullet(scene)
    bodies = [b for n, b in e.scene_info.facts["body_ids"].items() if n != "floor"]
    lo, hi = scene_bounds(e.client_id, bodies)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    cam = frame_camera(lo, hi)
    ndc = project(corners, *camera_matrices(cam))
    assert np.all(np.abs(ndc[:, :2]) <= 1.0) and np.all(np.abs(ndc[:, 2]) <= 1.0)
    span = max(np.ptp(ndc[:, 0]), np.ptp(ndc[:, 1]))  # of the view's width 2
    assert span >= 0.8
    # what the window showed before: the camera 5 m away (issue 17), the scene under 8 % of the view
    default = {"cameraDistance": 5.0, "cameraYaw": 50.0, "cameraPitch": -35.0, "cameraTargetPosition": [0, 0, 0]}
    assert max(np.ptp(project(corners, *camera_matrices(default))[:, :2], axis=0)) < 0.15
    assert p.isConnected(physicsClientId=e.client_id)


def test_the_view_puts_the_ghost_at_the_proxy_and_draws_one_normal_per_contact(make_pybullet):
    import pybullet as p

    from hapticproxy.clients.pybullet_gui import NORMAL_LENGTH_M, PybulletView

    e = make_pybullet("peg")
    cid = e.client_id
    bodies = [b for n, b in e.scene_info.facts["body_ids"].items() if n != "floor"]
    view = PybulletView(cid, bodies, ghost_boxes=[(0.01, 0.01, 0.03)])
    (ghost,) = view.ghost_bodies()
    q = (math.cos(0.2), 0.0, 0.0, math.sin(0.2))
    vs = ViewState(server_state=ServerState.ENGAGED, proxy_pose=np.array([0.01, -0.02, 0.07, *q]),
                   hand_wrench=np.array([0, 0, 0.5, 0, 0, 0.0]), tool_pose=e.tool_pose(np.zeros(7)), epsilon_m=EPS,
                   following=True, contact_position_m=np.array([[0.0, 0.0, 0.04], [0.01, 0.0, 0.04]]),
                   contact_normal=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]),
                   contact_separation_m=np.array([0.003, -0.001]))
    view.draw(vs)
    pos, orn = p.getBasePositionAndOrientation(ghost, physicsClientId=cid)
    np.testing.assert_allclose(pos, [0.01, -0.02, 0.07], atol=1e-9)
    np.testing.assert_allclose(orn, [q[1], q[2], q[3], q[0]], atol=1e-9)  # pybullet's x y z w
    (a0, b0, c0), (a1, b1, c1) = view.last_segments
    np.testing.assert_allclose(b0, np.array(a0) + [0, 0, NORMAL_LENGTH_M])
    assert c0 != c1  # predicted vs penetrating
    assert view.last_rgb == state_style(ServerState.ENGAGED)[1] and "contacts 2" in view.last_text
    rgba = p.getVisualShapeData(ghost, physicsClientId=cid)[0][7]
    assert rgba[2] > rgba[0]  # rendered: blue
    vs.server_state, vs.following = ServerState.FAULT, False
    view.draw(vs)
    rgba = p.getVisualShapeData(ghost, physicsClientId=cid)[0][7]
    assert rgba[0] > rgba[2] and view.last_text.startswith("FAULT")  # held: the fault's red
    # the ghost never becomes a contact, even where it overlaps the tool and the block
    from hapticproxy.clients.engine import ContactBuffer

    e.reset_tool_pose(np.array([0.0, 0.0, 0.041 + 0.03, 1.0, 0.0, 0.0, 0.0]))  # 1 mm above the block
    vs.proxy_pose = e.tool_pose(np.zeros(7)).copy()
    vs.proxy_pose[2] -= 0.002
    view.draw(vs)
    buf = ContactBuffer(16)
    n = e.contacts(buf, 16)
    assert n > 0 and ghost not in set(buf.keys[:n, 1].tolist())


# ------------------------------------------------------------------------------ quiet windows (issue 32, papercut 15)
def _run_python(code: str, env_extra: dict, drop=()) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(env_extra)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300,
                          env=env)


def test_the_pymunk_window_prints_nothing_and_leaves_the_sound_card_alone():
    """pygame's banner (stdout, at import) and pygame.init()'s mixer, which printed four ALSA
    errors on a machine without sound: the window opens the display and fonts only."""
    pytest.importorskip("pygame")
    out = _run_python("""
        from hapticproxy.clients.pymunk_engine import PymunkEngine
        e = PymunkEngine(gui=True)
        e.load_scene("wall")
        import pygame
        print("mixer", pygame.mixer.get_init(), "display", pygame.display.get_init(), flush=True)
        e.close()
        """, {"SDL_VIDEODRIVER": "dummy"}, drop=("SDL_AUDIODRIVER", "PYGAME_HIDE_SUPPORT_PROMPT"))
    assert out.returncode == 0, out.stderr
    assert out.stdout == "mixer None display True\n", out.stdout
    assert out.stderr == "", out.stderr


def test_the_c_stdout_is_muted_while_a_pybullet_gui_is_open_and_pythons_is_not():
    """pybullet's GUI prints its chatter on the C stdout, from its own thread too: fd 1 goes to
    /dev/null while a GUI is open; what Python prints still reaches the real stdout, in order."""
    pytest.importorskip("pybullet")
    out = _run_python("""
        import os, sys
        from hapticproxy.clients.pybullet_common import _mute_c_stdout
        print("before", flush=True)
        _mute_c_stdout(True)
        os.write(1, b"C chatter\\n")
        print("python while muted")
        _mute_c_stdout(False)
        os.write(1, b"C after\\n")
        print("python after")
        """, {})
    assert out.returncode == 0, out.stderr
    assert out.stdout == "before\npython while muted\nC after\npython after\n"


@pytest.mark.skipif(shutil.which("xvfb-run") is None,
                    reason="xvfb-run is not installed (Debian: apt-get install xvfb): pybullet's GUI needs a display")
def test_the_pybullet_client_window_prints_no_banner():
    """``client pybullet --gui`` on a virtual display: nothing from pybullet's GUI on stdout or
    stderr (it printed about 25 lines: threads, X11, the GL context, its shutdown)."""
    pytest.importorskip("pybullet")
    out = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 800x600x24", sys.executable, "-c", textwrap.dedent("""
        from hapticproxy.clients.pybullet_engine import PybulletEngine
        e = PybulletEngine(gui=True)
        e.load_scene("loose")
        for _ in range(30):
            e.step(1 / 60)
        e.close()
        print("closed")
        """)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout == "closed\n" and out.stderr == "", (out.stdout, out.stderr)


class _SpyP:
    """pybullet as the view sees it, with every debug line requested recorded."""

    def __init__(self, real) -> None:
        self._real = real
        self.lines: list = []

    def __getattr__(self, name):
        return getattr(self._real, name)

    def addUserDebugLine(self, a, b, rgb, width, **kw):  # noqa: N802 - pybullet's name
        self.lines.append((tuple(a), tuple(b), tuple(rgb)))
        return self._real.addUserDebugLine(a, b, rgb, width, **kw)


def test_the_pybullet_view_draws_the_normals_beside_the_tool_and_the_force_arrow_outside_it(make_pybullet,
                                                                                           monkeypatch):
    """A 40 mm cube resting on the floor, its four bottom corners in contact (normals +z), the
    hand feeling 0.5 N up: each normal is a line requested beside its corner, outside the cube
    (from the corner itself it ran up the cube's edge, hidden by its faces); the force arrow, a
    shaft and a four-line head, starts outside the ghost and points along the force."""
    import pybullet

    from hapticproxy.clients import pybullet_gui
    from hapticproxy.clients.pybullet_gui import (FORCE_M_PER_N, NORMAL_LENGTH_M, NORMAL_OFFSET_M,
                                                  PybulletView)
    from hapticproxy.clients.views import FORCE_RGB, contact_colour

    spy = _SpyP(pybullet)
    monkeypatch.setattr(pybullet_gui, "p", spy)
    e = make_pybullet("loose")
    half = 0.02
    bodies = [b for n, b in e.scene_info.facts["body_ids"].items() if n != "floor"]
    view = PybulletView(e.client_id, bodies, ghost_boxes=[(half, half, half)])
    corners = np.array([[sx * half, sy * half, 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    centre = np.array([0.0, 0.0, half])
    vs = ViewState(server_state=ServerState.ENGAGED, proxy_pose=np.array([*centre, 1.0, 0.0, 0.0, 0.0]),
                   hand_wrench=np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0]),
                   tool_pose=np.array([*centre, 1.0, 0.0, 0.0, 0.0]), epsilon_m=EPS, following=True,
                   contact_position_m=corners, contact_normal=np.tile([0.0, 0.0, 1.0], (4, 1)),
                   contact_separation_m=np.full(4, -0.0005))
    view.draw(vs)
    red = tuple(v / 255.0 for v in contact_colour(-0.0005))
    normals = [(np.array(a), np.array(b)) for a, b, rgb in spy.lines if rgb == red]
    assert len(normals) == 4
    for (a, b), c in zip(normals, corners):
        np.testing.assert_allclose(b - a, [0.0, 0.0, NORMAL_LENGTH_M], atol=1e-12)  # along the normal
        assert np.linalg.norm(a - c) == pytest.approx(NORMAL_OFFSET_M)             # beside its contact
        for q in (a, b, 0.5 * (a + b)):
            assert max(abs(q[0]), abs(q[1])) > half + 1e-3                          # outside the cube
    purple = tuple(v / 255.0 for v in FORCE_RGB)
    arrow = [(np.array(a), np.array(b)) for a, b, rgb in spy.lines if rgb == purple]
    assert len(arrow) == 5 and [(tuple(a), tuple(b)) for a, b in arrow] == view.last_arrow
    (s0, tip), head = arrow[0], arrow[1:]
    assert np.linalg.norm(s0 - centre) >= math.sqrt(3) * half - 1e-12            # outside the ghost
    np.testing.assert_allclose(tip - s0, [0.0, 0.0, FORCE_M_PER_N * 0.5], atol=1e-12)  # along the force
    assert all(np.allclose(a, tip) and b[2] < tip[2] for a, b in head)
    # no force, no contacts: every line collapses below the floor
    spy.lines.clear()
    vs.hand_wrench[:] = 0.0
    vs.contact_position_m, vs.contact_normal, vs.contact_separation_m = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    view.draw(vs)
    assert len(spy.lines) == 9 and all(a[2] == -10 and b[2] == -10 for a, b, _ in spy.lines)
