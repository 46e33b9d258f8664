"""An adversarial engine (test tool): the geometry an engine may send that stores energy in the
server's penalty springs, behind the ordinary :class:`~hapticproxy.clients.engine.Engine` interface
(issue 31, "Measure": geometry jumps up to 5 cm, flipped normals, objects driven into the tool).

The scene (planar, world frame, no gravity): a rectangular tool (``mass_kg``, ``size_m``) above a
floor, the half-plane ``y <= h(t)`` (body 1, contact normal +y), and a block, the half-plane
``x >= b(t)`` (body 2, normal -x), that starts ``BLOCK_GAP_M`` to the right of the tool. The
engine's tool follows the newest proxy pose rigidly (as the peg engine does) and is pushed out
of the floor and the block. A seeded schedule of events, drawn at :meth:`load_scene` over
``seconds`` (one every 0.15-0.6 s from ``first_s`` on):

- ``jump``: the floor moves by a uniform amount in [-5 cm, +5 cm] at once (two jumps in three
  go up, into the tool) and stays;
- ``flip``: the next 1-6 reported updates carry every normal reversed (the points and
  separations kept), as an engine's edge-edge normal without a fixed sign does;
- ``ram``: the block is driven into the tool at 0.05-0.5 m/s for 0.1-0.5 s (its ``v_constr`` is
  its speed along the normal: the engine says the object moves), then stops where it is.

Contacts: each corner of the tool within epsilon of the floor or of the block, keyed by (0, body,
corner). Deterministic for a seed and a sequence of ``drive_tool`` calls; ``events`` lists the
schedule, ``stats`` counts what was done.
"""
from __future__ import annotations

import math
import random

import numpy as np

from ..clients.engine import ContactBuffer, Engine, SceneInfo, ToolDescription, checked_epsilon, checked_step
from ..clients.geometry import planar_pose, planar_state

SCENES = ("adversary",)
JUMP_MAX_M = 0.05
BLOCK_GAP_M = 0.03


class AdversarialEngine(Engine):
    """See the module docstring."""

    name = "hapticproxy-adversary 1"
    deterministic = True

    def __init__(self, seed: int = 0, *, rate_hz: float = 60.0, seconds: float = 10.0, first_s: float = 0.3,
                 mass_kg: float = 0.25, size_m: tuple[float, float] = (0.04, 0.02)) -> None:
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 10_000.0):
            raise ValueError(f"rate_hz: must be in (0, 10000] Hz, got {rate_hz!r}")
        self.seed = int(seed)
        self.rate_hz = float(rate_hz)
        self.seconds = float(seconds)
        self.first_s = float(first_s)
        self.mass_kg = float(mass_kg)
        self.half = (0.5 * float(size_m[0]), 0.5 * float(size_m[1]))
        self._eps = 0.0
        self.events: list = []
        self.stats = {"jumps": 0, "flipped_updates": 0, "rams": 0, "jump_max_m": 0.0}
        self._q = [0.0, 0.0, 0.0]
        self._target = [0.0, 0.0, 0.0]
        self._t = 0.0

    @classmethod
    def scenes(cls) -> tuple[str, ...]:
        return SCENES

    def load_scene(self, name: str) -> SceneInfo:
        if name not in SCENES:
            raise ValueError(f"unknown scene {name!r} for engine adversary; choose one of: {', '.join(SCENES)}")
        rng = random.Random(self.seed)
        ev, t = [], self.first_s
        while t < self.seconds:
            kind = rng.choice(("jump", "jump", "flip", "ram"))
            if kind == "jump":
                up = rng.random() < 2.0 / 3.0
                ev.append((t, "jump", (1.0 if up else -1.0) * rng.uniform(0.0, JUMP_MAX_M)))
            elif kind == "flip":
                ev.append((t, "flip", float(rng.randint(1, 6))))
            else:
                ev.append((t, "ram", (rng.uniform(0.05, 0.5), rng.uniform(0.1, 0.5))))
            t += rng.uniform(0.15, 0.6)
        self.events = ev
        self._next = 0
        self._floor = 0.0
        hx, hy = self.half
        self._block = hx + BLOCK_GAP_M
        self._ram_speed = 0.0
        self._ram_until = -1.0
        self._flips_left = 0
        self._t = 0.0
        self._q = [0.0, hy + 0.001, 0.0]
        self._target = list(self._q)
        izz = self.mass_kg * (4 * hx * hx + 4 * hy * hy) / 12.0
        tool = ToolDescription("planar", self.mass_kg, (0.0, 0.0, 0.0), (0.0, 0.0, izz, 0.0, 0.0, 0.0))
        return SceneInfo(name, tool, env_rate_hz=self.rate_hz,
                         facts={"floor": "y <= h(t), normal +y", "block": "x >= b(t), normal -x",
                                "events": len(ev)})

    def set_epsilon(self, epsilon_m: float) -> None:
        self._eps = checked_epsilon(epsilon_m)

    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        x, y, th, *_ = planar_state(proxy_pose, proxy_twist)
        if math.isfinite(x) and math.isfinite(y) and math.isfinite(th):
            self._target = [x, y, th]

    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        return planar_pose(self._q[0], self._q[1], self._q[2], out)

    @property
    def time_s(self) -> float:
        return self._t

    def _corners(self, q) -> list:
        hx, hy = self.half
        c, s = math.cos(q[2]), math.sin(q[2])
        return [(q[0] + c * px - s * py, q[1] + s * px + c * py) for px, py in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]

    def step(self, dt_s: float) -> None:
        dt = checked_step(dt_s)
        self._t += dt
        while self._next < len(self.events) and self.events[self._next][0] <= self._t:
            _, kind, arg = self.events[self._next]
            self._next += 1
            if kind == "jump":
                self._floor += arg
                self.stats["jumps"] += 1
                self.stats["jump_max_m"] = max(self.stats["jump_max_m"], abs(arg))
            elif kind == "flip":
                self._flips_left = int(arg)
            else:
                self._ram_speed, self._ram_until = arg[0], self._t + arg[1]
                self.stats["rams"] += 1
        if self._t <= self._ram_until:
            self._block -= self._ram_speed * dt
        else:
            self._ram_speed = 0.0
        q = list(self._target)
        pts = self._corners(q)
        low = min(p[1] for p in pts)
        if low < self._floor:
            q[1] += self._floor - low
        right = max(p[0] for p in self._corners(q))
        if right > self._block:
            q[0] -= right - self._block
        self._q = q

    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        cap = min(max_contacts, buf.capacity)
        flip = -1.0 if self._flips_left > 0 else 1.0
        if self._flips_left > 0:
            self._flips_left -= 1
            self.stats["flipped_updates"] += 1
        n = 0
        for j, (px, py) in enumerate(self._corners(self._q)):
            for body, d, cp, nrm, vc in ((1, py - self._floor, (px, self._floor), (0.0, 1.0), 0.0),
                                         (2, self._block - px, (self._block, py), (-1.0, 0.0), self._ram_speed)):
                if d > self._eps or n >= cap:
                    continue
                buf.keys[n] = (0, body, j)
                buf.position_m[n] = (cp[0], cp[1], 0.0)
                buf.normal[n] = (flip * nrm[0], flip * nrm[1], 0.0)
                buf.separation_m[n] = d
                buf.v_constr_m_per_s[n] = vc
                n += 1
        buf.n = n
        return n
