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
import math
from dataclasses import dataclass, field

import numpy as np


#: Joint types of a linkage link (the protocol's JointType values).
from ..protocol.vocab import JOINT_TYPES_BY_NAME as JOINT_TYPES  # noqa: E402


def checked_epsilon(epsilon_m) -> float:
    """``epsilon_m`` [m] as a float; ``ValueError`` naming it unless finite and >= 0 (what every
    ``Engine.set_epsilon`` accepts)."""
    eps = float(epsilon_m)
    if not (math.isfinite(eps) and eps >= 0.0):
        raise ValueError(f"epsilon_m: must be a finite number >= 0, got {epsilon_m!r}")
    return eps


def checked_step(dt_s) -> float:
    """``dt_s`` [s] as a float; ``ValueError`` naming it unless finite and > 0 (what every
    ``Engine.step`` accepts)."""
    dt = float(dt_s)
    if not (math.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt_s: must be a finite number > 0, got {dt_s!r}")
    return dt


def checked_positive(**values) -> None:
    """``ValueError`` naming the first argument that is not a finite number > 0 (engines' settings)."""
    for name, v in values.items():
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name}: must be a finite number > 0, got {v!r}")


@dataclass(frozen=True)
class LinkDescription:
    """One link of a linkage tool, as ``Hello.links`` describes it (SPEC "Link record").

    Link 0 is the root (``parent = -1``, ``joint = "root"``): its frame is the tool frame. Every
    other link hangs from an earlier ``parent`` by a ``"revolute"`` or ``"prismatic"`` joint with
    the unit ``joint_axis`` in this link's frame; ``joint_origin`` (x y z qw qx qy qz) is this
    link's frame in the parent's at q = 0. ``com_m`` and ``inertia_kg_m2`` ([Ixx, Iyy, Izz, Ixy,
    Ixz, Iyz] about the COM) are in this link's frame."""

    mass_kg: float
    com_m: tuple = (0.0, 0.0, 0.0)
    inertia_kg_m2: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    parent: int = -1
    joint: str = "root"
    joint_axis: tuple = (0.0, 0.0, 1.0)
    joint_origin: tuple = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

    def record(self) -> dict:
        """The link record of ``Hello.links``."""
        if self.joint not in JOINT_TYPES:
            raise ValueError(f"joint: expected one of {', '.join(JOINT_TYPES)}, got {self.joint!r}")
        return dict(mass_kg=float(self.mass_kg), com_m=[float(v) for v in self.com_m],
                    inertia_kg_m2=[float(v) for v in self.inertia_kg_m2], parent=int(self.parent),
                    joint_type=JOINT_TYPES[self.joint], joint_axis=[float(v) for v in self.joint_axis],
                    joint_origin=[float(v) for v in self.joint_origin])


@dataclass(frozen=True)
class ToolDescription:
    """The virtual tool as the Hello describes it: a rigid body (``1dof``, ``planar``,
    ``spatial``) or a ``linkage`` (its ``links``, held by the hand at link ``held_link``'s frame
    origin; ``mass_kg`` is then the total, informative)."""

    kind: str  # "1dof" | "planar" | "spatial" | "linkage"
    mass_kg: float
    com_m: tuple = (0.0, 0.0, 0.0)  # tool frame
    #: [Ixx, Iyy, Izz, Ixy, Ixz, Iyz] about the COM, tool frame (planar: Izz is what matters)
    inertia_kg_m2: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    axis: tuple = (1.0, 0.0, 0.0)  # 1dof only
    links: tuple = ()  # linkage only: LinkDescription, root first
    held_link: int = 0  # linkage only


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
    #: the same constructor arguments (seed) and the same calls give bit-identical results (the
    #: contract suite checks an engine that says so)
    deterministic: bool = False

    @classmethod
    @abc.abstractmethod
    def scenes(cls) -> tuple[str, ...]:
        """Scene names this engine can load."""

    @abc.abstractmethod
    def load_scene(self, name: str) -> SceneInfo:
        """Build the scene; raise ``ValueError`` naming the choices if ``name`` is unknown."""

    @abc.abstractmethod
    def set_epsilon(self, epsilon_m: float) -> None:
        """Inflate the tool by a sphere of this radius for contact queries (the granted epsilon);
        ``ValueError`` for a negative or non-finite one (:func:`checked_epsilon`)."""

    def next_step_s(self) -> float | None:
        """Length [s] of the next step when the engine chooses it (variable-rate engines draw it
        here); ``None`` (the default) means a fixed step of ``1 / SceneInfo.env_rate_hz``."""
        return None

    @abc.abstractmethod
    def step(self, dt_s: float) -> None:
        """Advance the world by ``dt_s`` (the engine's own, possibly variable, step; :func:`checked_step`)."""

    @abc.abstractmethod
    def drive_tool(self, proxy_pose: np.ndarray, proxy_twist: np.ndarray, wrench: np.ndarray) -> None:
        """Make the engine's tool follow the proxy (pose (7,), twist (6,), world frame) without
        tunnelling or injecting energy; ``wrench`` (6,) is what the server says acts on the tool.
        A linkage: the root link's frame (``drive_joints`` came first with the joints). Driven to
        its own ``tool_pose`` with zero twist, the tool stays where it is (the runner holds it so
        while the server does not render the proxy)."""

    def drive_joints(self, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> None:
        """A linkage engine: the proxy's joint positions, rates and efforts (links 1..L-1), given
        just before ``drive_tool`` with the same ProxyState (empty arrays from a server that does
        not model the joints: keep the last targets). Rigid-tool engines never get it."""
        raise NotImplementedError(f"{type(self).__name__} has no linkage tool")

    def joint_positions(self, out: np.ndarray) -> np.ndarray:
        """A linkage engine: fill ``out`` (L-1,) with its own joint positions (those the contacts
        are computed at; sent as ``ContactUpdate.tool_joint_position``) and return it."""
        raise NotImplementedError(f"{type(self).__name__} has no linkage tool")

    def device_inputs(self, buttons: int, gripper_angle_rad: float, gripper_velocity_rad_per_s: float,
                      reported: int) -> None:
        """The haptic device's inputs of the newest ProxyState (protocol 1.3): ``buttons`` a bit
        mask (bit i: button i held), the gripper's angle and rate, ``reported`` which of them the
        device has (``ProxyState.device_inputs``: bit 0 buttons, 1 angle, 2 rate; 0 from an
        older server). Called by the runner for every ProxyState it takes, whatever the server's
        state, before ``drive_tool``. An engine uses them as the scene's controls (grasp while a
        button is held, ...). Default: nothing."""

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
