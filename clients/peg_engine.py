"""The paper's 1-DOF peg-in-hole (its Figs. 5, 6 and 9) as an engine behind the real protocol.

A 1 kg peg slides along the world x axis in a hole that fits it exactly: with its centre at
x = 0 both faces touch both walls; x > 0 penetrates the right wall, x < 0 the left one. The
tool is a ``1dof`` rigid body (axis +x, tool frame at the peg's centre).

The environment is the paper's: it has no dynamics of its own; each step it takes the newest
proxy position it was sent (the "model of the tool" the engine knows), and reports both walls
where they are within epsilon (the real tool's separation ``d``; ``d <= 0`` penetrating):

- left wall: body 1, constraint point ``(-w, 0, 0)``, normal ``+x``, ``d = x``;
- right wall: body 2, constraint point ``(+w, 0, 0)``, normal ``-x``, ``d = -x``;

with ``w`` the half-width (10 mm; only the constraint points depend on it). Its step is fixed,
``rate_hz`` (default 50 Hz: the paper's 20 ms environment period). The paper's 20 ms
environment *delay* is not modelled here: it is the network's, put between client and server
by the experiment (an impairing relay on UDP, a delayed queue in simulated time).
"""
from __future__ import annotations

import math

import numpy as np

from .engine import ContactBuffer, Engine, SceneInfo, ToolDescription, checked_epsilon, checked_step
from .geometry import axis_coordinate, axis_pose

#: the paper's Fig. 6 peg
PEG_MASS_KG = 1.0
#: half-width of the peg and the hole [m]
PEG_HALF_WIDTH_M = 0.01
_AXIS = (1.0, 0.0, 0.0)
SCENES = {"peg1d": "a 1-DOF peg (1 kg) exactly fitting a hole: both walls touch it at x = 0 (the paper's Figs. 5, 6, 9)"}


class PegEngine(Engine):
    """The 1-DOF peg-in-hole environment (see the module docstring)."""

    name = "hapticproxy-peg1d 1"
    deterministic = True

    def __init__(self, rate_hz: float = 50.0, *, mass_kg: float = PEG_MASS_KG) -> None:
        rate_hz = float(rate_hz)
        if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= 10_000.0):
            raise ValueError(f"rate_hz: must be in (0, 10000] Hz, got {rate_hz!r}")
        mass_kg = float(mass_kg)
        if not (math.isfinite(mass_kg) and mass_kg > 0.0):
            raise ValueError(f"mass_kg: must be a finite number > 0, got {mass_kg!r}")
        self.rate_hz = rate_hz
        self.mass_kg = mass_kg
        self._eps = 0.0
        self._x = 0.0          # the engine's tool position [m], world x
        self._target = 0.0     # the newest proxy position it was sent
        self._t = 0.0
        self._loaded = False
        self.steps = 0

    @classmethod
    def scenes(cls) -> tuple[str, ...]:
        return tuple(SCENES)

    def load_scene(self, name: str) -> SceneInfo:
        if name not in SCENES:
            raise ValueError(f"unknown scene {name!r} for engine peg1d; choose one of: {', '.join(SCENES)}")
        self._x = self._target = self._t = 0.0
        self.steps = 0
        self._loaded = True
        tool = ToolDescription("1dof", self.mass_kg, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), axis=_AXIS)
        return SceneInfo(name, tool, env_rate_hz=self.rate_hz,
                         facts={"half_width_m": PEG_HALF_WIDTH_M, "walls": "left x = -w (normal +x), right x = +w (normal -x)",
                                "description": SCENES[name]})

    def set_epsilon(self, epsilon_m: float) -> None:
        self._eps = checked_epsilon(epsilon_m)

    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        x = axis_coordinate(proxy_pose, _AXIS)
        if math.isfinite(x):  # a non-finite pose never reaches the geometry (the server never sends one)
            self._target = x

    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        return axis_pose(self._x, _AXIS, out)

    @property
    def time_s(self) -> float:
        return self._t

    def step(self, dt_s: float) -> None:
        dt_s = checked_step(dt_s)
        if not self._loaded:
            raise RuntimeError("load_scene first")
        self._x = self._target
        self._t += dt_s
        self.steps += 1

    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        n = 0
        w = PEG_HALF_WIDTH_M
        for body, cx, nx, d in ((1, -w, 1.0, self._x), (2, w, -1.0, -self._x)):
            if d > self._eps or n >= min(max_contacts, buf.capacity):
                continue
            buf.keys[n] = (0, body, 0)
            buf.position_m[n] = (cx, 0.0, 0.0)
            buf.normal[n] = (nx, 0.0, 0.0)
            buf.separation_m[n] = d
            buf.v_constr_m_per_s[n] = 0.0
            n += 1
        buf.n = n
        return n
