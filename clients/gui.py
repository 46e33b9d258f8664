"""Optional live window for the pymunk engine (``hapticproxy client pymunk --gui``; needs pygame,
the ``gui`` extra). Imported only when asked for.

Draws the world with pymunk's debug drawing, the proxy's outline (blue) and the reported contacts
(a dot at ``c_p`` and a 10 mm normal; red when the real tool penetrates, orange when the contact is
predicted, i.e. ``0 < d <= epsilon``). Screen +y is down, which is the world +y of the scenes
(the paper's Fig. 12 orientation). At most ``fps`` frames per second; closing the window or Esc
calls ``on_close`` (the CLI stops the client).
"""
from __future__ import annotations

import math
import time

import pygame
import pymunk
import pymunk.pygame_util

from .scenes import TOOL_LENGTH_M, TOOL_WIDTH_M

_PX_PER_M = 1800.0
_ORIGIN_PX = (450.0, 290.0)


class PymunkWindow:
    def __init__(self, engine, size_px: tuple[int, int] = (900, 680), fps: float = 60.0) -> None:
        pygame.init()
        self.engine = engine
        self.screen = pygame.display.set_mode(size_px)
        pygame.display.set_caption(f"hapticproxy client: {engine.name}")
        self.options = pymunk.pygame_util.DrawOptions(self.screen)
        self.options.transform = pymunk.Transform(a=_PX_PER_M, b=0.0, c=0.0, d=_PX_PER_M,
                                                  tx=_ORIGIN_PX[0], ty=_ORIGIN_PX[1])
        # pymunk's own collision points are drawn in pixels; scaled to metres they would span the
        # window, and the reported (epsilon) contacts are drawn below instead.
        self.options.flags = (pymunk.pygame_util.DrawOptions.DRAW_SHAPES
                              | pymunk.pygame_util.DrawOptions.DRAW_CONSTRAINTS)
        self.period_s = 1.0 / fps
        self._next_frame = 0.0
        self.last_contacts = None
        self.on_close = None

    @staticmethod
    def _px(x: float, y: float) -> tuple[int, int]:
        return int(round(_ORIGIN_PX[0] + _PX_PER_M * x)), int(round(_ORIGIN_PX[1] + _PX_PER_M * y))

    def draw(self) -> None:
        now = time.monotonic()
        if now < self._next_frame:
            return
        self._next_frame = now + self.period_s
        for event in pygame.event.get():
            if event.type == pygame.QUIT or (event.type == pygame.KEYDOWN and event.key == pygame.K_ESCAPE):
                if self.on_close is not None:
                    self.on_close()
        self.screen.fill((255, 255, 255))
        self.engine.space.debug_draw(self.options)
        if getattr(self.engine, "_linkage", False):  # the proxy's links
            frames = [t[:3] for t in self.engine.link_targets()]
            local = self.engine._link_local
        else:
            frames = [self.engine._target[:3]]
            a, b = TOOL_LENGTH_M / 2, TOOL_WIDTH_M / 2
            local = ((-a, -b), (a, -b), (a, b), (-a, b))
        for x, y, th in frames:
            c, s = math.cos(th), math.sin(th)
            outline = [self._px(x + c * lx - s * ly, y + s * lx + c * ly) for lx, ly in local]
            pygame.draw.polygon(self.screen, (40, 80, 220), outline, 1)
        if self.last_contacts is not None:
            pos, nor, sep = self.last_contacts
            for i in range(len(sep)):
                colour = (220, 30, 30) if sep[i] <= 0 else (240, 150, 20)
                p0 = self._px(pos[i, 0], pos[i, 1])
                p1 = self._px(pos[i, 0] + 0.01 * nor[i, 0], pos[i, 1] + 0.01 * nor[i, 1])
                pygame.draw.circle(self.screen, colour, p0, 3)
                pygame.draw.line(self.screen, colour, p0, p1, 1)
        pygame.display.flip()

    def close(self) -> None:
        pygame.display.quit()
        pygame.quit()
