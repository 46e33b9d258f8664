"""Optional live window for the pymunk engine (``hapticproxy client pymunk --gui``; needs pygame,
the ``gui`` extra, imported only when a window opens).

Each frame (what each shows and its colours: :mod:`.views`):

- the world (pymunk's debug drawing of the shapes and the drive's joints);
- the **epsilon band**: the engine's tool (every link) inflated by the granted epsilon, the
  region where a feature is reported as a predicted contact;
- the **proxy**: a translucent ghost of the tool (every link) at the newest ProxyState's pose
  (a linkage: its root and joints), blue while rendered, in the server state's colour while the
  server holds it;
- the reported **contacts**: a dot at ``c_p`` and a 10 mm normal, red penetrating, orange
  predicted;
- the **force on the hand** (minus ``ProxyState.wrench``) as an arrow from where the hand holds
  the proxy, :data:`FORCE_PX_PER_N` pixels per newton, and its value;
- the **server state** as a banner across the top (engaged green, fading orange, fault red with a
  red frame round the whole window, idle or no session grey).

Screen +y is down, which is the world +y of the scenes (the paper's Fig. 12 orientation). At
most ``fps`` frames per second; closing the window or Esc calls ``on_close`` (the CLI stops the
client). The geometry of a frame (:func:`inflated_outline`, :func:`tool_outlines`,
:class:`Viewport`) needs no pygame, and :meth:`PymunkWindow.render` draws one frame from a
:class:`~.views.ViewState`, so both are tested headless (``SDL_VIDEODRIVER=dummy``).
"""
from __future__ import annotations

import math
import os
import time

import numpy as np

from ..protocol.messages import ServerState

from .geometry import planar_angle, planar_chain
from .scenes import LINK_LENGTH_M, TOOL_LENGTH_M, TOOL_WIDTH_M
from .views import FORCE_RGB, PROXY_RGB, ViewState, contact_colour, state_style, view_state

__all__ = ["PymunkWindow", "Viewport", "inflated_outline", "tool_outlines", "FORCE_PX_PER_N", "EPSILON_RGB",
           "FORCE_RGB", "BANNER_PX"]

#: arrow length per newton of the force on the hand [px/N] (at most :data:`_MAX_ARROW_PX`)
FORCE_PX_PER_N = 120.0
_MAX_ARROW_PX = 250.0
EPSILON_RGB = (120, 190, 255)
BACKGROUND_RGB = (255, 255, 255)
#: height of the state banner across the top [px]
BANNER_PX = 28
_FAULT_FRAME_PX = 6
_GHOST_ALPHA = 90
_NORMAL_LENGTH_M = 0.01


class Viewport:
    """World metres to screen pixels: ``px = origin + scale * world`` on both axes (screen +y down
    = world +y)."""

    def __init__(self, px_per_m: float = 1800.0, origin_px: tuple[float, float] = (450.0, 290.0)) -> None:
        self.px_per_m = float(px_per_m)
        self.origin_px = (float(origin_px[0]), float(origin_px[1]))

    def px(self, x: float, y: float) -> tuple[int, int]:
        return (int(round(self.origin_px[0] + self.px_per_m * x)), int(round(self.origin_px[1] + self.px_per_m * y)))


def inflated_outline(vertices, epsilon_m: float, segments_per_corner: int = 6) -> list[tuple[float, float]]:
    """Outline of a convex polygon (``vertices`` counter-clockwise, world) swept by a disc of
    radius ``epsilon_m``: every edge pushed out by epsilon, joined by arcs round the corners."""
    v = [(float(x), float(y)) for x, y in vertices]
    m = len(v)
    if epsilon_m <= 0.0:
        return v
    normals = []
    for j in range(m):
        ex, ey = v[(j + 1) % m][0] - v[j][0], v[(j + 1) % m][1] - v[j][1]
        length = math.hypot(ex, ey)
        normals.append((ey / length, -ex / length))  # counter-clockwise: outward = edge rotated by -90 deg
    out = []
    for i in range(m):
        a0 = math.atan2(normals[i - 1][1], normals[i - 1][0])
        a1 = math.atan2(normals[i][1], normals[i][0])
        while a1 < a0:
            a1 += 2.0 * math.pi
        for k in range(segments_per_corner + 1):
            a = a0 + (a1 - a0) * k / segments_per_corner
            out.append((v[i][0] + epsilon_m * math.cos(a), v[i][1] + epsilon_m * math.sin(a)))
    return out


def _placed(local, x: float, y: float, th: float) -> list[tuple[float, float]]:
    c, s = math.cos(th), math.sin(th)
    return [(x + c * lx - s * ly, y + s * lx + c * ly) for lx, ly in local]


def tool_outlines(linkage: bool, link_local, pose, joint_position) -> list[list[tuple[float, float]]]:
    """World polygons of the tool (one per link) at a tool pose (x y z qw qx qy qz) and, for the
    linkage, its joint positions."""
    root = (float(pose[0]), float(pose[1]), planar_angle(pose), 0.0, 0.0, 0.0)
    if linkage:
        frames = planar_chain(root, joint_position, np.zeros(len(joint_position)), LINK_LENGTH_M)
        return [_placed(link_local, f[0], f[1], f[2]) for f in frames]
    a, b = TOOL_LENGTH_M / 2, TOOL_WIDTH_M / 2
    return [_placed(((-a, -b), (a, -b), (a, b), (-a, b)), root[0], root[1], root[2])]


def hand_point(linkage: bool, pose, joint_position) -> tuple[float, float]:
    """Where the hand holds the proxy (world x, y): the tool frame's origin, a linkage's last link's."""
    root = (float(pose[0]), float(pose[1]), planar_angle(pose), 0.0, 0.0, 0.0)
    if linkage:
        f = planar_chain(root, joint_position, np.zeros(len(joint_position)), LINK_LENGTH_M)[-1]
        return f[0], f[1]
    return root[0], root[1]


class PymunkWindow:
    """The window (see the module docstring). ``update(runner)`` draws a frame of the runner's
    session (rate-limited); ``render(view_state)`` draws one frame unconditionally."""

    def __init__(self, engine, size_px: tuple[int, int] = (900, 680), fps: float = 60.0,
                 viewport: Viewport | None = None) -> None:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")  # its banner on stdout, at import
        import pygame
        import pymunk.pygame_util

        self._pg = pygame
        # the window and its text only: pygame.init() would also open the sound card, and print
        # ALSA's errors on a machine that has none
        pygame.display.init()
        pygame.font.init()
        self.engine = engine
        self.viewport = viewport or Viewport()
        self.screen = pygame.display.set_mode(size_px)
        pygame.display.set_caption(f"hapticproxy client: {engine.name}")
        self.options = pymunk.pygame_util.DrawOptions(self.screen)
        vp = self.viewport
        self.options.transform = pymunk.Transform(a=vp.px_per_m, b=0.0, c=0.0, d=vp.px_per_m,
                                                  tx=vp.origin_px[0], ty=vp.origin_px[1])
        # pymunk's own collision points are drawn in pixels; scaled to metres they would span the
        # window, and the reported (epsilon) contacts are drawn instead.
        self.options.flags = (pymunk.pygame_util.DrawOptions.DRAW_SHAPES
                              | pymunk.pygame_util.DrawOptions.DRAW_CONSTRAINTS)
        self._overlay = pygame.Surface(size_px, pygame.SRCALPHA)
        self._font = pygame.font.Font(None, 24)
        self.period_s = 1.0 / fps
        self._next_frame = 0.0
        self.on_close = None
        self.frames = 0

    # ------------------------------------------------------------------ frames
    def update(self, runner, force: bool = False) -> bool:
        """Handle window events and draw the runner's session, at most ``fps`` times a second
        (unless ``force``); returns whether it drew."""
        now = time.monotonic()
        if not force and now < self._next_frame:
            return False
        self._next_frame = now + self.period_s
        pg = self._pg
        for event in pg.event.get():
            if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key == pg.K_ESCAPE):
                if self.on_close is not None:
                    self.on_close()
        self.render(view_state(runner))
        pg.display.flip()
        return True

    def render(self, vs: ViewState) -> None:
        """Draw one frame of ``vs`` onto :attr:`screen` (not flipped)."""
        pg = self._pg
        screen = self.screen
        vp = self.viewport
        engine = self.engine
        linkage = bool(getattr(engine, "_linkage", False))
        link_local = getattr(engine, "_link_local", None)
        screen.fill(BACKGROUND_RGB)
        engine.space.debug_draw(self.options)
        label, rgb = state_style(vs.server_state)
        # the epsilon band round the engine's tool (where it is, not where the proxy is)
        if vs.tool_pose is not None:
            joints = engine.joint_positions(np.zeros(len(engine.links) - 1)) if linkage else ()
            for poly in tool_outlines(linkage, link_local, vs.tool_pose, joints):
                band = inflated_outline(poly, vs.epsilon_m)
                pg.draw.lines(screen, EPSILON_RGB, True, [vp.px(x, y) for x, y in band], 1)
        # the proxy's ghost
        if vs.proxy_pose is not None:
            ghost = PROXY_RGB if vs.following else rgb
            overlay = self._overlay
            overlay.fill((0, 0, 0, 0))
            for poly in tool_outlines(linkage, link_local, vs.proxy_pose, vs.proxy_joint_position):
                pts = [vp.px(x, y) for x, y in poly]
                pg.draw.polygon(overlay, ghost + (_GHOST_ALPHA,), pts)
                pg.draw.polygon(overlay, ghost + (255,), pts, 1)
            screen.blit(overlay, (0, 0))
        # the reported contacts
        for c, nrm, d in zip(vs.contact_position_m, vs.contact_normal, vs.contact_separation_m):
            colour = contact_colour(float(d))
            p0 = vp.px(c[0], c[1])
            p1 = vp.px(c[0] + _NORMAL_LENGTH_M * nrm[0], c[1] + _NORMAL_LENGTH_M * nrm[1])
            pg.draw.circle(screen, colour, p0, 3)
            pg.draw.line(screen, colour, p0, p1, 1)
        # the force on the hand
        force_n = float(math.hypot(vs.hand_wrench[0], vs.hand_wrench[1]))
        if vs.proxy_pose is not None and force_n > 1e-6:
            hx, hy = hand_point(linkage, vs.proxy_pose, vs.proxy_joint_position)
            start = vp.px(hx, hy)
            length = min(_MAX_ARROW_PX, FORCE_PX_PER_N * force_n)
            ux, uy = vs.hand_wrench[0] / force_n, vs.hand_wrench[1] / force_n
            tip = (start[0] + length * ux, start[1] + length * uy)
            pg.draw.line(screen, FORCE_RGB, start, tip, 3)
            head = 10.0
            left = (tip[0] - head * ux + 0.5 * head * uy, tip[1] - head * uy - 0.5 * head * ux)
            right = (tip[0] - head * ux - 0.5 * head * uy, tip[1] - head * uy + 0.5 * head * ux)
            pg.draw.polygon(screen, FORCE_RGB, [tip, left, right])
        # the server state
        width, height = screen.get_size()
        pg.draw.rect(screen, rgb, (0, 0, width, BANNER_PX))
        text = (f"{label}    force on the hand {force_n:.2f} N    contacts {len(vs.contact_separation_m)}    "
                f"epsilon {vs.epsilon_m * 1e3:g} mm")
        screen.blit(self._font.render(text, True, (255, 255, 255)), (8, 6))
        if vs.server_state == ServerState.FAULT:
            pg.draw.rect(screen, rgb, (0, 0, width, height), _FAULT_FRAME_PX)
        self.frames += 1

    def close(self) -> None:
        self._pg.display.quit()
        self._pg.quit()
