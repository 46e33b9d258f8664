"""The engine interface: what the engine-neutral client loop needs from a physics engine.

One module per engine implements :class:`Engine` (``stub``, ``pymunk``, ``pybullet``). The shared
loop (handshake, stepping at the engine's own rate, sending a ``ContactUpdate`` after every step,
applying the newest ``ProxyState``, heartbeats, reconnecting) never imports an engine.

Conventions (the protocol's, see ``protocol/SPEC.md``): SI units, world frame; poses are
``x y z qw qx qy qz`` of the *tool frame*; contact normals point from the environment towards the
tool; ``separation_m`` is the *real* tool's separation (``s_eps + epsilon``), positive apart.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ToolDescription:
    """The virtual tool as the Hello describes it (rigid kinds; linkages come later)."""

    kind: str  # "1dof" | "planar" | "spatial"
    mass_kg: float
    com_m: tuple = (0.0, 0.0, 0.0)  # tool frame
    #: [Ixx, Iyy, Izz, Ixy, Ixz, Iyz] about the COM, tool frame (planar: Izz is what matters)
    inertia_kg_m2: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    axis: tuple = (1.0, 0.0, 0.0)  # 1dof only


class ContactBuffer:
    """Preallocated contact arrays an engine fills (row i = contact i, the first ``n`` valid)."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity: must be >= 1, got {capacity}")
        self.capacity = capacity
        self.keys = np.zeros((capacity, 3), dtype=np.int64)  # (tool_link, env_body, feature)
        self.position_m = np.zeros((capacity, 3))  # constraint point on the environment, world
        self.normal = np.zeros((capacity, 3))  # unit, environment -> tool, world
        self.separation_m = np.zeros(capacity)  # real tool separation, + apart, - penetrating
        self.v_constr_m_per_s = np.zeros(capacity)  # n . v(c_p) of the environment point
        self.n = 0


@dataclass
class SceneInfo:
    """What ``load_scene`` reports about the scene it built."""

    name: str
    tool: ToolDescription
    #: nominal step rate of the engine for this scene [Hz] (informative; Hello.env_rate_hz)
    env_rate_hz: float = 60.0
    #: free-form facts worth printing (dimensions, where the walls are), SI units
    facts: dict = field(default_factory=dict)


class Engine(abc.ABC):
    """A physics engine with one virtual tool in one scene."""

    #: engine name and version for Hello.engine, e.g. "pymunk 7.3.1"
    name: str = "engine"

    @classmethod
    @abc.abstractmethod
    def scenes(cls) -> tuple[str, ...]:
        """Scene names this engine can load."""

    @abc.abstractmethod
    def load_scene(self, name: str) -> SceneInfo:
        """Build the scene; raise ``ValueError`` naming the choices if ``name`` is unknown."""

    @abc.abstractmethod
    def set_epsilon(self, epsilon_m: float) -> None:
        """Inflate the tool by a sphere of this radius for contact queries (the granted epsilon)."""

    def next_step_s(self) -> float | None:
        """Length [s] of the next step when the engine chooses it (variable-rate engines draw it
        here); ``None`` (the default) means a fixed step of ``1 / SceneInfo.env_rate_hz``."""
        return None

    @abc.abstractmethod
    def step(self, dt_s: float) -> None:
        """Advance the world by ``dt_s`` (the engine's own, possibly variable, step)."""

    @abc.abstractmethod
    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        """Make the engine's tool follow the proxy (pose (7,), twist (6,), world frame) without
        tunnelling or injecting energy; ``wrench`` (6,) is what the server says acts on the tool."""

    @abc.abstractmethod
    def tool_pose(self, out: np.ndarray) -> np.ndarray:
        """Fill and return ``out`` (7,) with the engine's tool pose (tool frame, world)."""

    @abc.abstractmethod
    def contacts(self, buf: ContactBuffer, max_contacts: int) -> int:
        """Fill ``buf`` with the epsilon-active contacts (at most ``max_contacts``, clustered when
        there are more); set and return ``buf.n``. Keys must be unique and stable across steps."""

    @property
    @abc.abstractmethod
    def time_s(self) -> float:
        """Simulation time [s]."""

    def warm_up(self) -> None:
        """Pay one-time costs (JIT compilation, caches) now: the runner calls this once before it
        connects, so the first steps of a session are not late. Default: nothing."""

    def close(self) -> None:
        """Release the engine (windows, physics servers)."""
