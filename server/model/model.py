"""The local model of interaction: a thin class that owns the preallocated arrays and calls one
numba kernel per haptic step (``step``) and one per model update (``update``).

Typical use, one haptic step at a time::

    model = LocalModel(ToolSpec.planar(mass_kg=0.2, inertia_kg_m2=2e-4),
                       ContactParams(stiffness_n_per_m=4000, damping_n_s_per_m=30),
                       period_s=1 / 512)
    model.update(keys, position_m, normal, separation_m, v_constr_m_per_s)   # at 30-60 Hz
    wrench_to_hand = model.step(hand_wrench)                                  # every step

Bad input raises ``ValueError`` naming the field and leaves the model exactly as it was.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ...protocol.quaternion import quat_to_matrix_into

from ..readonly import ArrayFloat, ArrayInt, frozen_copies
from . import kernels as _k
from . import linkage as _lk
from .slot import descriptor as slot_descriptor, new_slot
from .layout import (
    C_CP, C_D, C_DEF, C_FN, C_FT, C_IMP, C_N, C_P, C_REC, C_S, C_SPREV, C_TU, C_VC, C_VN, C_Z,
    CI_AGE, CI_KEY, CI_SLIP, CI_STATE, CONTACT_STATE_NAMES, E_OK, ERROR_FIELDS,
    K_COLLISIONS, K_DEFORMED, K_DROPPED, K_FLIPS, K_FLIPS_TAKEN, K_HELD, K_LEFT, K_RECOVERING, K_REKEYED, K_M, K_N_COLLIDING, K_N_IMPENDING,
    K_N_PENETRATING, K_N_SEPARATING, K_NEW, K_NONFINITE, K_PROXY, K_RANK, K_SLIPPING, K_STEPS,
    K_UPDATES, NCOLS_F, NCOLS_I, NCOUNT, NPAR, NSTATE,
    P_AXIS, P_B, P_BT, P_DT, P_E, P_EPS, P_GRAV, P_HAND, P_INERTIA, P_K, P_KT, P_MASS, P_MUK,
    P_MUS, P_ORIGIN, P_POLICY, POLICY_PAPER_LITERAL, P_CPL_BR, P_CPL_BT, P_CPL_KR, P_CPL_KT, P_INTEG,
    INTEGRATOR_NAMES, K_DIVERGED, K_OSC_RUN, P_REC_AGE, P_REC_FRATE, P_REC_TAU, P_REC_V, P_REC_VN, POLICY_NAMES, PROXY_STATE_NAMES,
    S_EREC, S_RECF, S_FENV, S_FIMP, S_FPEN, S_GIMP, S_KE, S_KE_POST, S_KE_PRE, S_LQ, S_Q, S_QD, S_QDP, S_T,
    TOOL_1DOF, TOOL_DIMS, TOOL_KIND_NAMES, TOOL_LINKAGE, TOOL_PLANAR, TOOL_SPATIAL, UNIT_TOL,
    JT_PRISMATIC, JT_REVOLUTE, JT_ROOT, LI_CHAIN, LI_NCHAIN, LI_PARENT, LI_TYPE,
    LK_AXIS, LK_COM, LK_I, LK_MASS, LK_OP, LK_OR, LM_D, LM_H, LM_HELD, LM_NLINKS, LM_NQR, LM_PLANAR,
    LM_COR, LM_R, LW_P, LW_R, MAX_DOF, NLI, NLK, NLM, NLW,
)

_F64 = np.dtype(np.float64)
DEFAULT_CAPACITY = 64
#: Most contacts one update may carry before the capacity rule; larger sets are refused.
DEFAULT_MAX_UPDATE_CONTACTS = 1024
#: Deformation recovery defaults (``LocalModel(recovery_...)``; EXPERIMENTS.md, "Deformation
#: recovery", says how they were chosen): a deformed contact that has persisted 10 model updates
#: (0.17-0.33 s at 30-60 Hz) is brought back to the true geometry at up to 25 mm/s, the
#: penalty force this adds at a fixed pose changing by at most 200 N/s in total (0.2 N per step
#: at 1 kHz: a fifth of the safety layer's 1000 N/s), the last part exponentially (tau 0.1 s).
RECOVERY_SPEED_M_PER_S = 0.025
RECOVERY_FORCE_RATE_N_PER_S = 200.0
RECOVERY_TAU_S = 0.1
RECOVERY_MIN_AGE_UPDATES = 10
#: ... and only while the proxy rests on the contact: its normal speed there at most this many
#: times the recovery speed (it may move out as fast as the recovery moves it). Without this gate
#: the recovery also pushed while the hand shook the 1-DOF peg of Fig. 6 against a wall (LM0),
#: and fed the shaking: the excursion grew by 2x within 8 s at gates of 1.6x and more.
RECOVERY_RESTING_SPEED_FACTOR = 1.2
#: ``linkage_dynamics``: "full" includes the velocity-product (Coriolis, centripetal, gyroscopic)
#: terms of a linkage's eq. 7; "paper" neglects them as the paper does (see ``linkage.py``).
LINKAGE_DYNAMICS = ("full", "paper")


def _finite_float(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: must be finite, got {v!r}")
    return v


def _vec3(name: str, value) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name}: expected 3 numbers, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: must be finite, got {a.tolist()}")
    return a


JOINT_TYPES = {"root": JT_ROOT, "revolute": JT_REVOLUTE, "prismatic": JT_PRISMATIC}


@dataclass(frozen=True)
class LinkSpec:
    """One link of a linkage tool: the protocol's link record (``Hello.links``) in SI units.

    Link 0 is the root (``parent = -1``, ``joint = "root"``): the floating base, whose frame is
    the tool frame. Every other link hangs from an earlier ``parent`` by a ``"revolute"`` (q in
    rad, right-handed about ``axis``) or ``"prismatic"`` (q in m along ``axis``) joint; ``axis``
    is a unit vector in this link's frame; ``origin_m`` / ``origin_quat`` (w x y z) are this
    link's frame in the parent's frame at q = 0. ``com_m`` and ``inertia_kg_m2`` (about the COM;
    3x3, or 3 principal moments) are in this link's frame.
    """

    mass_kg: float
    com_m: tuple = (0.0, 0.0, 0.0)
    inertia_kg_m2: tuple = (0.0, 0.0, 0.0)
    parent: int = -1
    joint: str = "root"
    axis: tuple = (0.0, 0.0, 1.0)
    origin_m: tuple = (0.0, 0.0, 0.0)
    origin_quat: tuple = (1.0, 0.0, 0.0, 0.0)

    def inertia_matrix(self) -> np.ndarray:
        a = np.asarray(self.inertia_kg_m2, dtype=np.float64)
        return np.diag(a) if a.shape == (3,) else a


def linkage_dims(n_links: int, planar: bool) -> tuple[int, int, int]:
    """(d, h, nq) of a linkage with ``n_links`` links: the root's 3 (6) velocity coordinates plus
    one per joint; hand space 3 (6); position coordinates 3 (7) plus one per joint."""
    j = n_links - 1
    return (3 + j, 3, 3 + j) if planar else (6 + j, 6, 7 + j)


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w x y z), for set-up code: the protocol's one
    convention (:func:`hapticproxy.protocol.quaternion.quat_to_matrix_into`)."""
    return quat_to_matrix_into(np.asarray(q, dtype=np.float64), np.empty((3, 3)))


def _validate_links(links, held_link, planar: bool) -> None:
    """ValueError naming ``tool.links[i].field`` for anything the linkage kernels cannot model."""
    if not isinstance(links, (tuple, list)) or not links:
        raise ValueError("tool.links: a linkage needs at least one link (the root)")
    n = len(links)
    limit = MAX_DOF - (3 if planar else 6) + 1
    if n > limit:
        raise ValueError(f"tool.links: a {'planar' if planar else 'spatial'} linkage has at most {limit} links "
                         f"({limit - 1} joints: configuration space <= {MAX_DOF}), got {n}")
    if not isinstance(held_link, (int, np.integer)) or not 0 <= held_link < n:
        raise ValueError(f"tool.held_link: expected a link index in 0..{n - 1}, got {held_link!r}")
    for i, ln in enumerate(links):
        f = f"tool.links[{i}]"
        if not isinstance(ln, LinkSpec):
            raise ValueError(f"{f}: expected a LinkSpec, got {type(ln).__name__}")
        mass = _finite_float(f"{f}.mass_kg", ln.mass_kg)
        if not mass > 0:
            raise ValueError(f"{f}.mass_kg: must be positive, got {mass!r}")
        _vec3(f"{f}.com_m", ln.com_m)
        inertia = np.asarray(ln.inertia_kg_m2, dtype=np.float64)
        if inertia.shape == (3,):
            inertia = np.diag(inertia)
        if inertia.shape != (3, 3) or not np.all(np.isfinite(inertia)):
            raise ValueError(f"{f}.inertia_kg_m2: expected 3 finite moments or a finite 3x3 matrix")
        if not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-15):
            raise ValueError(f"{f}.inertia_kg_m2: must be symmetric")
        if planar:
            # only I_zz enters a planar linkage; it must be positive or D(q) can be singular
            if not inertia[2, 2] > 0:
                raise ValueError(f"{f}.inertia_kg_m2: I_zz must be positive for a planar linkage, got {inertia[2, 2]!r}")
        elif not np.all(np.linalg.eigvalsh(inertia) > 0):
            raise ValueError(f"{f}.inertia_kg_m2: must be positive definite (every link's inertia enters D(q))")
        if ln.joint not in JOINT_TYPES:
            raise ValueError(f"{f}.joint: expected one of {sorted(JOINT_TYPES)}, got {ln.joint!r}")
        if i == 0:
            if ln.parent != -1 or ln.joint != "root":
                raise ValueError(f"{f}: link 0 must be the root (parent -1, joint 'root')")
            continue
        if not isinstance(ln.parent, (int, np.integer)) or not 0 <= ln.parent < i:
            raise ValueError(f"{f}.parent: must be an earlier link (0 <= parent < {i}), got {ln.parent!r}")
        if ln.joint == "root":
            raise ValueError(f"{f}.joint: only link 0 may be the root")
        axis = _vec3(f"{f}.axis", ln.axis)
        if abs(np.linalg.norm(axis) - 1.0) > UNIT_TOL:
            raise ValueError(f"{f}.axis: must be a unit vector, got {axis.tolist()}")
        origin = _vec3(f"{f}.origin_m", ln.origin_m)
        quat = np.asarray(ln.origin_quat, dtype=np.float64)
        if quat.shape != (4,) or not np.all(np.isfinite(quat)) or abs(np.linalg.norm(quat) - 1.0) > UNIT_TOL:
            raise ValueError(f"{f}.origin_quat: must be a unit quaternion (w x y z), got {np.ravel(quat).tolist()}")
        if planar:
            # everything must stay in the x-y plane: frames rotate about z only, no z offsets
            if abs(quat[1]) > UNIT_TOL or abs(quat[2]) > UNIT_TOL:
                raise ValueError(f"{f}.origin_quat: a planar linkage's frames may only rotate about +z")
            if abs(origin[2]) > 1e-9:
                raise ValueError(f"{f}.origin_m: a planar linkage has no z offsets, got z = {origin[2]!r}")
            if ln.joint == "revolute" and abs(abs(axis[2]) - 1.0) > UNIT_TOL:
                raise ValueError(f"{f}.axis: a planar revolute joint turns about +-z, got {axis.tolist()}")
            if ln.joint == "prismatic" and abs(axis[2]) > UNIT_TOL:
                raise ValueError(f"{f}.axis: a planar prismatic joint slides in the x-y plane, got {axis.tolist()}")


@dataclass(frozen=True)
class ToolSpec:
    """The virtual tool the proxy stands for. Build with ``one_dof``, ``planar``, ``spatial`` or
    ``linkage``.

    ``inertia_kg_m2`` is about the centre of mass in the body frame (3x3); ``hand_point_m`` is
    where the hand holds the tool, body frame (the hand wrench acts there). A 1-DOF tool
    translates along the unit world ``axis`` and has its COM at ``origin_m + q * axis``. A
    linkage is its ``links`` (``LinkSpec``); the hand holds link ``held_link`` at its frame
    origin; ``planar`` selects the planar (x-y, about +z) or the spatial model.
    """

    kind: str
    mass_kg: float
    inertia_kg_m2: tuple = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    axis: tuple = (1.0, 0.0, 0.0)
    origin_m: tuple = (0.0, 0.0, 0.0)
    hand_point_m: tuple = (0.0, 0.0, 0.0)
    links: tuple = ()
    held_link: int = 0
    planar: bool = False

    @classmethod
    def one_dof(cls, mass_kg: float, axis=(1.0, 0.0, 0.0), origin_m=(0.0, 0.0, 0.0)) -> "ToolSpec":
        return cls("1dof", mass_kg, axis=tuple(axis), origin_m=tuple(origin_m))

    @classmethod
    def planar(cls, mass_kg: float, inertia_kg_m2: float, hand_point_m=(0.0, 0.0)) -> "ToolSpec":
        """Rigid body in the x-y plane; ``inertia_kg_m2`` is I_zz about the COM."""
        izz = float(inertia_kg_m2)
        hp = tuple(hand_point_m) + (0.0,) * (3 - len(tuple(hand_point_m)))
        return cls("planar", mass_kg, inertia_kg_m2=((izz, 0, 0), (0, izz, 0), (0, 0, izz)), hand_point_m=hp)

    @classmethod
    def spatial(cls, mass_kg: float, inertia_kg_m2, hand_point_m=(0.0, 0.0, 0.0)) -> "ToolSpec":
        """Rigid body in 3-D; ``inertia_kg_m2``: 3x3 matrix or 3 principal moments."""
        inertia = np.asarray(inertia_kg_m2, dtype=np.float64)
        if inertia.shape == (3,):
            inertia = np.diag(inertia)
        return cls("spatial", mass_kg, inertia_kg_m2=tuple(map(tuple, inertia.tolist())),
                   hand_point_m=tuple(hand_point_m))

    @classmethod
    def linkage(cls, links, held_link: int, planar: bool) -> "ToolSpec":
        """A kinematic tree of ``LinkSpec`` (link 0 the floating root), held by ``held_link`` at
        its frame origin; ``planar``: the x-y plane model (revolute joints about z)."""
        links = tuple(links)
        mass = sum(float(ln.mass_kg) for ln in links if isinstance(ln, LinkSpec)) or 1.0
        return cls("linkage", mass, links=links, held_link=held_link, planar=bool(planar))

    @property
    def kind_id(self) -> int:
        return TOOL_KIND_NAMES[self.kind]

    def validated(self) -> None:
        if self.kind not in TOOL_KIND_NAMES:
            raise ValueError(f"tool.kind: expected one of {sorted(TOOL_KIND_NAMES)}, got {self.kind!r}")
        if self.kind == "linkage":
            _validate_links(self.links, self.held_link, self.planar)
            return
        if self.links:
            raise ValueError("tool.links: only a linkage tool has links")
        mass = _finite_float("tool.mass_kg", self.mass_kg)
        if not mass > 0:
            raise ValueError(f"tool.mass_kg: must be positive, got {mass!r}")
        inertia = np.asarray(self.inertia_kg_m2, dtype=np.float64)
        if inertia.shape != (3, 3) or not np.all(np.isfinite(inertia)):
            raise ValueError("tool.inertia_kg_m2: expected a finite 3x3 matrix")
        if self.kind == "planar" and not inertia[2, 2] > 0:
            raise ValueError(f"tool.inertia_kg_m2: I_zz must be positive, got {inertia[2, 2]!r}")
        if self.kind == "spatial":
            if not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-15):
                raise ValueError("tool.inertia_kg_m2: must be symmetric")
            if not np.all(np.linalg.eigvalsh(inertia) > 0):
                raise ValueError("tool.inertia_kg_m2: must be positive definite (negative or zero inertia)")
        axis = _vec3("tool.axis", self.axis)
        if self.kind == "1dof" and abs(np.linalg.norm(axis) - 1.0) > UNIT_TOL:
            raise ValueError(f"tool.axis: must be a unit vector, got {axis.tolist()}")
        _vec3("tool.origin_m", self.origin_m)
        _vec3("tool.hand_point_m", self.hand_point_m)


@dataclass(frozen=True)
class ContactParams:
    """Dynamic properties shared by all local contacts (section III-A of the paper)."""

    stiffness_n_per_m: float = 4000.0
    damping_n_s_per_m: float = 30.0
    restitution: float = 0.0
    mu_static: float = 0.0
    mu_kinetic: float = 0.0
    #: Stiffness of the stick spring of the friction model; None: the contact stiffness.
    tangential_stiffness_n_per_m: float | None = None
    #: Damping of the stick spring while sticking; None: the contact damping.
    tangential_damping_n_s_per_m: float | None = None

    def validated(self) -> None:
        for name in ("stiffness_n_per_m", "damping_n_s_per_m", "mu_static", "mu_kinetic"):
            v = _finite_float(f"contact.{name}", getattr(self, name))
            if v < 0:
                raise ValueError(f"contact.{name}: must be >= 0, got {v!r}")
        e = _finite_float("contact.restitution", self.restitution)
        if not 0.0 <= e <= 1.0:
            raise ValueError(f"contact.restitution: must be in [0, 1], got {e!r}")
        if self.mu_kinetic > self.mu_static:
            raise ValueError(f"contact.mu_kinetic: must not exceed mu_static ({self.mu_kinetic!r} > {self.mu_static!r})")
        for name in ("tangential_stiffness_n_per_m", "tangential_damping_n_s_per_m"):
            v = getattr(self, name)
            if v is not None and not _finite_float(f"contact.{name}", v) >= 0:
                raise ValueError(f"contact.{name}: must be >= 0, got {v!r}")


#: The explicit haptic step (``integrator="explicit"``, semi-implicit Euler with every force
#: explicit, the paper's) is unstable beyond these for a contact acting through the tool's COM:
#: the spring when omega dt > 2 (k dt^2 / m > 4), the damper when it overshoots (b dt / m > 2).
#: Necessary, not sufficient: a contact far from the COM of a tool with a small inertia has a
#: smaller effective mass, and the coupling's damper acts too (EXPERIMENTS.md, "Light tools").
#: The implicit step (the default) has no such limit (``check_proxy_inertia``).
STEP_K_DT2_PER_M_MAX = 4.0
STEP_B_DT_PER_M_MAX = 2.0


def check_step_stability(mass_kg: float, contact: "ContactParams", period_s: float) -> None:
    """Refuse contact parameters the explicit haptic step cannot integrate stably for a rigid tool
    of ``mass_kg`` (``ValueError`` naming the field, the ratio, the limit and what would do)."""
    m = float(mass_kg)
    dt = float(period_s)
    rate = 1.0 / dt
    pairs = [("stiffness_n_per_m", contact.stiffness_n_per_m, "damping_n_s_per_m", contact.damping_n_s_per_m)]
    if contact.tangential_stiffness_n_per_m is not None or contact.tangential_damping_n_s_per_m is not None:
        pairs.append(("tangential_stiffness_n_per_m", contact.tangential_stiffness_n_per_m or 0.0,
                      "tangential_damping_n_s_per_m", contact.tangential_damping_n_s_per_m or 0.0))
    for kname, k, bname, b in pairs:
        rk = k * dt * dt / m
        if rk > STEP_K_DT2_PER_M_MAX:
            raise ValueError(
                f"contact.{kname}: {k:g} N/m on a {m:g} kg tool at {rate:g} Hz is beyond what the haptic step "
                f"integrates stably (k dt^2 / m = {rk:.3g} > {STEP_K_DT2_PER_M_MAX:g}): at most "
                f"{STEP_K_DT2_PER_M_MAX * m / (dt * dt):.4g} N/m at this rate, or a rate of at least "
                f"{math.sqrt(k / (STEP_K_DT2_PER_M_MAX * m)):.4g} Hz")
        rb = b * dt / m
        if rb > STEP_B_DT_PER_M_MAX:
            raise ValueError(
                f"contact.{bname}: {b:g} N s/m on a {m:g} kg tool at {rate:g} Hz is beyond what the haptic step "
                f"integrates stably (b dt / m = {rb:.3g} > {STEP_B_DT_PER_M_MAX:g}): at most "
                f"{STEP_B_DT_PER_M_MAX * m / dt:.4g} N s/m at this rate, or a rate of at least "
                f"{b / (STEP_B_DT_PER_M_MAX * m):.4g} Hz")


#: The lightest tools the implicit step (``integrator="implicit"``) is stable for, as measured: a
#: rigid tool of 1e-12 kg and 1e-18 kg m^2 comes to rest on a floor under a 1 N push on every
#: kind at 500 Hz and 4 kHz with the default coupling and contacts (tests/model/light_rig.py);
#: these floors keep three and three orders of magnitude from there (below them, the rendering's
#: J_h D^-1 J_h^T nears the float range). A linkage's links: a chain of 1 g links settles there,
#: one of 0.3 g links keeps rocking after 3 s at 500 Hz and one of 3 mg links is thrown about
#: (tens of rad/s): its free links have no damping of their own, so each link must have at least
#: LINK_MASS_MIN_KG (and LINK_INERTIA_MIN_KG_M2 in every moment that enters its D(q)).
TOOL_MASS_MIN_KG = 1e-9
TOOL_INERTIA_MIN_KG_M2 = 1e-15
LINK_MASS_MIN_KG = 1e-3
LINK_INERTIA_MIN_KG_M2 = 1e-9


def check_proxy_inertia(tool: "ToolSpec") -> None:
    """Refuse a tool lighter than the implicit step was measured stable for (``ValueError``
    naming the field, the value and the smallest that works): a rigid tool's mass and principal
    moments (a 1dof tool's mass only; a planar tool's I_zz), each link of a linkage."""
    if tool.kind == "linkage":
        for i, ln in enumerate(tool.links):
            if float(ln.mass_kg) < LINK_MASS_MIN_KG:
                # a Reject's reason is cut at 120 characters (protocol.session): the smallest value
                # that works comes within them
                raise ValueError(
                    f"tool.links[{i}].mass_kg: {float(ln.mass_kg):g} kg is too light: an undamped link is thrown "
                    f"about by its contacts; at least {LINK_MASS_MIN_KG:g} kg")
            # a planar link turns about z only; a spatial one about every axis
            least = ln.inertia_matrix()[2, 2] if tool.planar else float(np.linalg.eigvalsh(ln.inertia_matrix())[0])
            if least < LINK_INERTIA_MIN_KG_M2:
                raise ValueError(
                    f"tool.links[{i}].inertia_kg_m2: a moment of {least:g} kg m^2 is below what a link may have; "
                    f"at least {LINK_INERTIA_MIN_KG_M2:g} kg m^2")
        return
    if float(tool.mass_kg) < TOOL_MASS_MIN_KG:
        raise ValueError(f"tool.mass_kg: {float(tool.mass_kg):g} kg is below the lightest tool the haptic step "
                         f"is stable for; at least {TOOL_MASS_MIN_KG:g} kg")
    if tool.kind == "1dof":
        return
    inertia = np.asarray(tool.inertia_kg_m2, dtype=np.float64)
    least = inertia[2, 2] if tool.kind == "planar" else float(np.linalg.eigvalsh(inertia)[0])
    if least < TOOL_INERTIA_MIN_KG_M2:
        raise ValueError(f"tool.inertia_kg_m2: a moment of {least:g} kg m^2 is below what the haptic step holds "
                         f"stably; at least {TOOL_INERTIA_MIN_KG_M2:g} kg m^2")


@dataclass
class ContactSnapshot:
    """A copy of the live local contacts (for tests, telemetry and plots; not for the hot path)."""

    keys: np.ndarray
    position_m: np.ndarray
    normal: np.ndarray
    separation_reported_m: np.ndarray
    v_constr_m_per_s: np.ndarray
    local_point_body_m: np.ndarray
    separation_m: np.ndarray
    separation_prev_m: np.ndarray
    normal_velocity_m_per_s: np.ndarray
    normal_force_n: np.ndarray
    friction_force_n: np.ndarray
    bristle_m: np.ndarray
    impulse_n_s: np.ndarray
    state: list = field(default_factory=list)
    slipping: np.ndarray | None = None
    age_updates: np.ndarray | None = None
    #: deformation the update rules put in, and advance the passivity layer held back, that the
    #: recovery has not yet taken back, m (>= 0)
    deformation_m: np.ndarray | None = None
    #: deformation taken back by the recovery since the contact's last update, less the advance
    #: the layer held back, m (negative while the held part exceeds what was recovered)
    recovered_m: np.ndarray | None = None


class LocalModel:
    """The paper's local model for one tool: rigid (1-DOF, planar or spatial) or a linkage.

    A linkage's q is (root pose, joints) and its qd (root origin velocity, root angular velocity,
    joint rates), see ``linkage.py``; its contacts are located on the link in key column 0, and
    the hand wrench acts at the held link's frame origin. Rigid tools step through
    ``kernels.step_rigid`` and never touch the linkage code.

    Parameters
    ----------
    tool: the virtual tool (mass, inertia, hand point).
    contact: stiffness, damping, restitution and friction of the local contacts.
    period_s: the haptic step.
    integrator: ``"implicit"`` (default): the step treats its spring-dampers (the controller's
        coupling, ``set_coupling``; the contacts; sticking friction) implicitly, stable for any
        tool at least ``check_proxy_inertia``'s floors; ``"explicit"``: semi-implicit Euler with
        every force explicit (the paper's step), stable within ``check_step_stability``.
    policy: ``"rigid"`` (eq. 1 at every update: the no-deformation baseline), ``"lm0"`` (proxy
        deformation, eqs. 4/5/6, with active geometry only: epsilon must be 0) or ``"lm"`` (proxy
        deformation with epsilon-active geometry, any epsilon >= 0; alias ``"deformation"``).
    epsilon_m: the epsilon granted to the engine (it inflates its tool; the model only records it).
    capacity: most local contacts kept; an update with more keeps the smallest separations
        and counts the rest in ``counters()["dropped"]``.
    gravity_m_per_s2: world gravity acting on the proxy (default none: the device carries it).
    linkage_dynamics: a linkage's eq. 7 with its velocity-product terms (``"full"``, default) or
        without them as the paper writes it (``"paper"``); ignored for rigid tools.
    recovery_speed_m_per_s, recovery_force_rate_n_per_s, recovery_tau_s, recovery_min_age_updates:
        deformation recovery (``set_recovery``); speed 0 turns it off (the paper's eq. 5 keeps a
        deformation for as long as the contact lasts).
    warm: compile / load the cached kernels now, not at the first haptic step.
    """

    def __init__(
        self,
        tool: ToolSpec,
        contact: ContactParams = ContactParams(),
        *,
        period_s: float = 1e-3,
        policy: str = "deformation",
        epsilon_m: float = 0.0,
        capacity: int = DEFAULT_CAPACITY,
        gravity_m_per_s2: Sequence[float] = (0.0, 0.0, 0.0),
        max_update_contacts: int = DEFAULT_MAX_UPDATE_CONTACTS,
        linkage_dynamics: str = "full",
        recovery_speed_m_per_s: float = RECOVERY_SPEED_M_PER_S,
        recovery_force_rate_n_per_s: float = RECOVERY_FORCE_RATE_N_PER_S,
        recovery_tau_s: float = RECOVERY_TAU_S,
        recovery_min_age_updates: int = RECOVERY_MIN_AGE_UPDATES,
        recovery_normal_speed_max_m_per_s: float | None = None,
        integrator: str = "implicit",
        warm: bool = True,
    ) -> None:
        tool.validated()
        contact.validated()
        dt = _finite_float("period_s", period_s)
        if not dt > 0:
            raise ValueError(f"period_s: must be positive, got {dt!r}")
        if policy not in POLICY_NAMES:
            raise ValueError(f"policy: expected one of {sorted(POLICY_NAMES)}, got {policy!r}")
        eps = _finite_float("epsilon_m", epsilon_m)
        if eps < 0:
            raise ValueError(f"epsilon_m: must be >= 0, got {eps!r}")
        if policy == "lm0" and eps != 0.0:
            raise ValueError(f"epsilon_m: policy 'lm0' is the local model with epsilon = 0, got {eps!r}")
        if not isinstance(capacity, (int, np.integer)) or capacity < 1:
            raise ValueError(f"capacity: must be a positive integer, got {capacity!r}")
        if not isinstance(max_update_contacts, (int, np.integer)) or max_update_contacts < capacity:
            raise ValueError(f"max_update_contacts: must be an integer >= capacity, got {max_update_contacts!r}")
        if integrator not in INTEGRATOR_NAMES:
            raise ValueError(f"integrator: expected one of {sorted(INTEGRATOR_NAMES)}, got {integrator!r}")
        if integrator == "explicit":
            if tool.kind in ("1dof", "planar", "spatial"):
                check_step_stability(tool.mass_kg, contact, dt)
        else:
            check_proxy_inertia(tool)
        grav = _vec3("gravity_m_per_s2", gravity_m_per_s2)
        if linkage_dynamics not in LINKAGE_DYNAMICS:
            raise ValueError(f"linkage_dynamics: expected one of {LINKAGE_DYNAMICS}, got {linkage_dynamics!r}")

        self.tool = tool
        self.contact = contact
        self.kind = tool.kind_id
        self.is_linkage = self.kind == TOOL_LINKAGE
        if self.is_linkage:
            self.dof, self.hand_dim, self.nq = linkage_dims(len(tool.links), tool.planar)
        else:
            self.dof, self.hand_dim, self.nq = TOOL_DIMS[self.kind]
        self.capacity = int(capacity)
        self.policy = policy

        par = np.zeros(NPAR)
        par[P_DT] = dt
        par[P_K] = contact.stiffness_n_per_m
        par[P_B] = contact.damping_n_s_per_m
        par[P_E] = contact.restitution
        par[P_MUS] = contact.mu_static
        par[P_MUK] = contact.mu_kinetic
        par[P_KT] = (contact.stiffness_n_per_m if contact.tangential_stiffness_n_per_m is None
                     else contact.tangential_stiffness_n_per_m)
        par[P_BT] = (contact.damping_n_s_per_m if contact.tangential_damping_n_s_per_m is None
                     else contact.tangential_damping_n_s_per_m)
        par[P_MASS] = tool.mass_kg
        par[P_INERTIA:P_INERTIA + 9] = np.asarray(tool.inertia_kg_m2, dtype=np.float64).ravel()
        par[P_GRAV:P_GRAV + 3] = grav
        par[P_AXIS:P_AXIS + 3] = tool.axis
        par[P_ORIGIN:P_ORIGIN + 3] = tool.origin_m
        par[P_HAND:P_HAND + 3] = tool.hand_point_m
        par[P_POLICY] = POLICY_NAMES[policy]
        par[P_EPS] = eps
        par[P_INTEG] = INTEGRATOR_NAMES[integrator]
        self.integrator = integrator
        self._par = par
        self.set_recovery(recovery_speed_m_per_s, recovery_force_rate_n_per_s, recovery_tau_s,
                          recovery_min_age_updates, recovery_normal_speed_max_m_per_s)
        self._st = np.zeros(NSTATE)
        self._C = np.zeros((self.capacity, NCOLS_F))
        self._CI = np.zeros((self.capacity, NCOLS_I), dtype=np.int64)
        self._cnt = np.zeros(NCOUNT, dtype=np.int64)
        self._wk = np.zeros(_k.workspace_size(self.capacity))
        self._hand = np.zeros(6)
        #: the update slot (``slot.py``): what the server's tick applies updates from; its
        #: scratch arrays are the update kernel's here too
        self.slot = new_slot(int(max_update_contacts), self.capacity, self.nq,
                             len(tool.links) if self.is_linkage else 0)
        self._slot_desc = slot_descriptor(self.slot)
        self._sel = self.slot.sel
        self._newF = self.slot.newF
        self._newI = self.slot.newI
        self._qe = np.zeros(7)  # placeholder engine configuration when none is given
        self._st_e = self.slot.st_e
        self._Re = self.slot.Re
        self._ce = self.slot.ce
        self._fenv = self._st[S_FENV:S_FENV + self.hand_dim]
        self._q_at = S_Q
        if self.is_linkage:
            self._lmeta, self._lk, self._lki = linkage_arrays(tool, linkage_dynamics == "full")
            self._lw = np.zeros((len(tool.links), NLW))
            self._lw_e = self.slot.lw_e
            self._qe = np.zeros(self.nq)
            self._q_at = S_LQ
            # a bound method per instance: rigid models keep the class's step, untouched
            self.step = self._step_linkage
        self.reset()
        if warm:
            warm_up()

    # -- state ---------------------------------------------------------------------------------
    def reset(self, q: Sequence[float] | None = None, qd: Sequence[float] | None = None) -> None:
        """Put the proxy at configuration q with velocity qd, empty the contact store, zero time.
        Spatial q is (x, y, z, qw, qx, qy, qz); it is normalised. A linkage's q is its root pose
        (planar x, y, theta; spatial x, y, z, qw, qx, qy, qz) then one value per joint."""
        qv = np.zeros(self.nq)
        spatial_root = self.kind == TOOL_SPATIAL or (self.is_linkage and not self.tool.planar)
        if spatial_root:
            qv[3] = 1.0
        if q is not None:
            qa = np.asarray(q, dtype=np.float64).ravel()
            if qa.shape != (self.nq,) or not np.all(np.isfinite(qa)):
                raise ValueError(f"q: expected {self.nq} finite numbers for a {self.tool.kind} tool")
            qv = qa.copy()
            if spatial_root:
                nrm = np.linalg.norm(qv[3:7])
                if not nrm > 0:
                    raise ValueError("q: the orientation quaternion must be non-zero")
                qv[3:7] /= nrm
        qdv = np.zeros(self.dof)
        if qd is not None:
            qda = np.asarray(qd, dtype=np.float64).ravel()
            if qda.shape != (self.dof,) or not np.all(np.isfinite(qda)):
                raise ValueError(f"qd: expected {self.dof} finite numbers for a {self.tool.kind} tool")
            qdv = qda
        self._st[:] = 0.0
        self._st[self._q_at:self._q_at + self.nq] = qv
        self._st[S_QD:S_QD + self.dof] = qdv
        self._C[:] = 0.0
        self._CI[:] = 0
        self._cnt[:] = 0

    def set_recovery(self, speed_m_per_s: float, force_rate_n_per_s: float = RECOVERY_FORCE_RATE_N_PER_S,
                     tau_s: float = RECOVERY_TAU_S, min_age_updates: int = RECOVERY_MIN_AGE_UPDATES,
                     normal_speed_max_m_per_s: float | None = None) -> None:
        """Deformation recovery. The update rules (eqs. 4/5) keep a late contact's penetration by
        moving the proxy's local contact point out along the normal; for updates that carry the
        engine's tool pose (the engine contact frame: where the true geometry is known relative to
        the proxy; never with the paper's eq. 1), while such a contact persists
        (at least ``min_age_updates`` model updates) and touches, its constraint is moved back
        towards the true geometry at up to ``speed_m_per_s``, the penalty force this adds at a
        fixed pose changing by at most ``force_rate_n_per_s`` summed over the recovering contacts,
        the last part exponentially with ``tau_s`` (0: linear to the end), and only while the
        proxy rests on the contact: its normal speed there at most ``normal_speed_max_m_per_s``
        (``None``: ``RECOVERY_RESTING_SPEED_FACTOR`` x ``speed_m_per_s``; 0: any speed).
        ``speed_m_per_s`` = 0: off. Applies from the next step; ``ValueError`` naming the field,
        nothing changed."""
        v = _finite_float("recovery_speed_m_per_s", speed_m_per_s)
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"recovery_speed_m_per_s: must be in [0, 1] m/s, got {v!r}")
        fr = _finite_float("recovery_force_rate_n_per_s", force_rate_n_per_s)
        tau = _finite_float("recovery_tau_s", tau_s)
        vn = (RECOVERY_RESTING_SPEED_FACTOR * v if normal_speed_max_m_per_s is None
              else _finite_float("recovery_normal_speed_max_m_per_s", normal_speed_max_m_per_s))
        if not 0.0 <= vn <= 10.0:
            raise ValueError(f"recovery_normal_speed_max_m_per_s: must be in [0, 10] m/s, got {vn!r}")
        if not fr > 0.0:
            raise ValueError(f"recovery_force_rate_n_per_s: must be positive, got {fr!r}")
        if not 0.0 <= tau <= 10.0:
            raise ValueError(f"recovery_tau_s: must be in [0, 10] s, got {tau!r}")
        if not isinstance(min_age_updates, (int, np.integer)) or not 0 <= min_age_updates <= 10_000:
            raise ValueError(f"recovery_min_age_updates: must be an integer in [0, 10000], got {min_age_updates!r}")
        p = self._par
        p[P_REC_V] = v
        p[P_REC_FRATE] = fr
        p[P_REC_TAU] = tau
        p[P_REC_AGE] = float(min_age_updates)
        p[P_REC_VN] = vn

    def set_coupling(self, stiffness_n_per_m: float = 0.0, damping_n_s_per_m: float = 0.0,
                     rot_stiffness_n_m_per_rad: float = 0.0, rot_damping_n_m_s_per_rad: float = 0.0) -> None:
        """The spring-damper through which a controller drives the proxy's hand point (the hand
        wrench of ``step`` then contains ``K (x_dev - x_hand) + B (v_dev - v_hand)``): the implicit
        integrator takes it into the step's matrix, so a light tool on a stiff coupling stays
        stable. ``control.haptic_step`` writes it every step it drives the proxy; a caller that
        steps the model with its own coupling calls this. Zeros (the default): no coupling.
        ``ValueError`` naming the field, nothing changed."""
        vals = []
        for name, v in (("stiffness_n_per_m", stiffness_n_per_m), ("damping_n_s_per_m", damping_n_s_per_m),
                        ("rot_stiffness_n_m_per_rad", rot_stiffness_n_m_per_rad),
                        ("rot_damping_n_m_s_per_rad", rot_damping_n_m_s_per_rad)):
            x = _finite_float(f"coupling.{name}", v)
            if x < 0:
                raise ValueError(f"coupling.{name}: must be >= 0, got {x!r}")
            vals.append(x)
        p = self._par
        p[P_CPL_KT], p[P_CPL_BT], p[P_CPL_KR], p[P_CPL_BR] = vals

    @property
    def coupling(self) -> dict:
        """The coupling the step's matrix holds (``set_coupling``; the controller's, once it drove)."""
        p = self._par
        return {"stiffness_n_per_m": float(p[P_CPL_KT]), "damping_n_s_per_m": float(p[P_CPL_BT]),
                "rot_stiffness_n_m_per_rad": float(p[P_CPL_KR]), "rot_damping_n_m_s_per_rad": float(p[P_CPL_BR])}

    @property
    def diverged(self) -> bool:
        """The proxy's velocity flipped sign every step without decaying for ``DIVERGE_STEPS`` steps
        in a row, at some time since ``reset`` (``layout.DIVERGE_*``): its integration went
        unstable; what it renders is not the tool's. Latched for the model's life. The loop
        reads the counter ``K_DIVERGED`` of ``kernel_args()[5]`` (non-zero)."""
        return int(self._cnt[K_DIVERGED]) > 0

    def settle(self) -> None:
        """Stop the proxy where it is (zero velocity, the divergence watch's run cleared; the
        contacts and ``diverged`` kept): what a re-arm after a divergence starts from. A proxy
        whose integration is unstable diverges again, and is flagged again, within
        ``DIVERGE_STEPS`` steps."""
        self._st[S_QD:S_QD + self.dof] = 0.0
        self._st[S_QDP:S_QDP + self.dof] = 0.0
        self._cnt[K_OSC_RUN] = 0

    @property
    def recovery(self) -> dict:
        """The deformation recovery settings (``set_recovery``)."""
        p = self._par
        return {"speed_m_per_s": float(p[P_REC_V]), "force_rate_n_per_s": float(p[P_REC_FRATE]),
                "tau_s": float(p[P_REC_TAU]), "min_age_updates": int(p[P_REC_AGE]),
                "normal_speed_max_m_per_s": float(p[P_REC_VN])}

    def read_eq6_literally(self) -> None:
        """Reproductions of the paper's Fig. 14 numbers only (``experiments``; the server never
        calls it): from the next update on, the update rules render the epsilon-inflated tool
        (``s - epsilon`` of eq. 6 with ``s`` the reported real-tool separation) and place new
        contacts by eq. 6 too (no eq. 4). Deformation recovery is turned off (the paper has none)
        and the step is the paper's (``integrator="explicit"``). A rigid policy stays rigid."""
        if self._par[P_POLICY] != 0.0:
            self._par[P_POLICY] = float(POLICY_PAPER_LITERAL)
            self.policy = "paper-literal"
        self.set_recovery(0.0)
        self._par[P_INTEG] = INTEGRATOR_NAMES["explicit"]
        self.integrator = "explicit"

    @property
    def recovering(self) -> int:
        """Contacts whose deformation the last step was recovering."""
        return int(self._cnt[K_RECOVERING])

    @property
    def held(self) -> int:
        """Contacts whose constraint's advance into the tool the last step held back (the
        passivity layer's set-position modulation, ``P_REC_CUT``)."""
        return int(self._cnt[K_HELD])

    @property
    def recovery_force_step_n(self) -> float:
        """Penalty force the recovery added at the last step at a fixed pose (k x the distance
        recovered, summed over the contacts), N: at most ``force_rate_n_per_s`` x the period."""
        return float(self._st[S_RECF])

    @property
    def recovery_energy_j(self) -> float:
        """Work the deformation recovery did on the proxy since ``reset`` (sum over steps of the
        normal force times the distance recovered), J: the energy it gave the user."""
        return float(self._st[S_EREC])

    def stop(self) -> None:
        """Bring the proxy to rest where it is (its velocity to zero; contacts and pose kept): the
        server holds the proxy while nothing is rendered."""
        self._st[S_QD:S_QD + self.dof] = 0.0

    # -- the two operations --------------------------------------------------------------------
    def update(self, keys, position_m, normal, separation_m, v_constr_m_per_s=None, tool_q=None) -> None:
        """Replace the local contacts by the engine's set (world frame, SI units).

        keys: (n, 3) int (tool link, environment body, feature); position_m: (n, 3) constraint
        positions c_p; normal: (n, 3) unit normals, environment towards tool; separation_m: (n,)
        real-tool separation d (negative when penetrating); v_constr_m_per_s: (n,) n . v(c_p);
        tool_q: the engine's tool configuration (like ``q``) at which they were computed, or
        ``None`` for the paper's eq. 1 (see ``update_arrays``).
        """
        qe = None
        if tool_q is not None:
            qe = np.asarray(tool_q, dtype=np.float64).ravel()
            if qe.shape != (self.nq,) or not np.all(np.isfinite(qe)):
                raise ValueError(f"tool_q: expected {self.nq} finite numbers for a {self.tool.kind} tool")
            if self.kind == TOOL_SPATIAL or (self.is_linkage and not self.tool.planar):
                nrm_q = np.linalg.norm(qe[3:7])
                if not nrm_q > 0:
                    raise ValueError("tool_q: the orientation quaternion must be non-zero")
                qe = qe.copy()
                qe[3:7] /= nrm_q
        keys = np.asarray(keys)
        n_in = keys.shape[0] if keys.ndim == 2 else -1
        if keys.ndim != 2 or keys.shape[1] != 3 or not np.issubdtype(keys.dtype, np.integer):
            if not (keys.size == 0 and keys.ndim in (1, 2)):
                raise ValueError(f"keys: expected an (n, 3) integer array, got {keys.dtype} {keys.shape}")
            n_in = 0
            keys = np.zeros((0, 3), dtype=np.int64)
        cp = self._as_f64("position_m", position_m, (n_in, 3))
        nrm = self._as_f64("normal", normal, (n_in, 3))
        dsep = self._as_f64("separation_m", separation_m, (n_in,))
        vc = (np.zeros(n_in) if v_constr_m_per_s is None
              else self._as_f64("v_constr_m_per_s", v_constr_m_per_s, (n_in,)))
        if n_in > self._sel.shape[0]:
            raise ValueError(f"contacts: {n_in} exceeds max_update_contacts={self._sel.shape[0]}")
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        code = self.update_arrays(keys, cp, nrm, dsep, vc, n_in, qe)
        if code != E_OK:
            fld, why = ERROR_FIELDS[code]
            raise ValueError(f"{fld}: {why}")

    def update_arrays(self, keys, position_m, normal, separation_m, v_constr_m_per_s, n: int,
                      tool_q: np.ndarray | None = None) -> int:
        """Hot-path variant of ``update`` for already-validated, preallocated arrays (the first n
        rows are used); returns the kernel's E_* code instead of raising.

        ``tool_q`` (float64[nq], finite, checked by the caller): the engine's tool configuration
        (COM pose, like ``q``) at which the contacts were computed. Given, the reported feature
        points are taken in the engine tool's frame and carried onto the proxy, so the proxy
        feels the geometry where the engine has it even when the engine's tool lags the proxy
        or is held back by what it touches. ``None``: the paper's eq. 1 (relative to the proxy)."""
        use = 0 if tool_q is None else 1
        if self.is_linkage:
            return _lk.update_linkage(self._par, self._lmeta, self._lk, self._lki, self._st, self._C, self._CI,
                                      self._cnt, self._wk, self._lw, keys, position_m, normal, separation_m,
                                      v_constr_m_per_s, n, self._sel, self._newF, self._newI,
                                      self._qe if tool_q is None else tool_q, use, self._lw_e)
        return _k.update_rigid(self.kind, self._par, self._st, self._C, self._CI, self._cnt, self._wk,
                               keys, position_m, normal, separation_m, v_constr_m_per_s, n,
                               self._sel, self._newF, self._newI,
                               self._qe if tool_q is None else tool_q, use, self._st_e, self._Re, self._ce)

    def step(self, hand_wrench) -> np.ndarray:
        """Advance one haptic step with the hand wrench on the proxy (world frame, at the hand
        point; 1dof: (f,), planar: (fx, fy, tau_z), spatial: (fx, fy, fz, tx, ty, tz)).
        Returns the environment wrench for the hand (a view, overwritten next step)."""
        # the server's path (a preallocated float64 array) is checked without building objects
        hand = hand_wrench if (type(hand_wrench) is np.ndarray and hand_wrench.dtype is _F64
                               and len(hand_wrench) >= self.hand_dim) else self._copy_hand(hand_wrench)
        code = _k.step_rigid(self.kind, self._par, self._st, self._C, self._CI, self._cnt, self._wk, hand)
        if code != E_OK:
            fld, why = ERROR_FIELDS[code]
            raise ValueError(f"{fld}: {why}")
        return self._fenv

    def _step_linkage(self, hand_wrench) -> np.ndarray:
        """``step`` of a linkage (the hand wrench acts at the held link's frame origin)."""
        hand = hand_wrench if (type(hand_wrench) is np.ndarray and hand_wrench.dtype is _F64
                               and len(hand_wrench) >= self.hand_dim) else self._copy_hand(hand_wrench)
        code = _lk.step_linkage(self._par, self._lmeta, self._lk, self._lki, self._st, self._C, self._CI,
                                self._cnt, self._wk, self._lw, hand)
        if code != E_OK:
            fld, why = ERROR_FIELDS[code]
            raise ValueError(f"{fld}: {why}")
        return self._fenv

    def _copy_hand(self, hand_wrench) -> np.ndarray:
        a = np.asarray(hand_wrench, dtype=np.float64).ravel()
        if a.shape != (self.hand_dim,):
            raise ValueError(f"hand_wrench: expected {self.hand_dim} numbers for a {self.tool.kind} tool, got {a.shape}")
        self._hand[:self.hand_dim] = a
        return self._hand

    def _as_f64(self, name, value, shape):
        a = np.asarray(value, dtype=np.float64)
        if a.size == 0 and shape[0] == 0:
            return np.zeros(shape)
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
        return np.ascontiguousarray(a)

    # -- read-outs -----------------------------------------------------------------------------
    period_s = ArrayFloat("_par", P_DT, doc="Haptic step, s.")
    time_s = ArrayFloat("_st", S_T, doc="Model time, s.")

    @property
    def q(self) -> np.ndarray:
        return self._st[self._q_at:self._q_at + self.nq]

    @property
    def qd(self) -> np.ndarray:
        return self._st[S_QD:S_QD + self.dof]

    @property
    def env_wrench(self) -> np.ndarray:
        """Total wrench rendered to the hand at the last step: penalty/friction + impulsive."""
        return self._fenv

    @property
    def impulsive_wrench(self) -> np.ndarray:
        return self._st[S_FIMP:S_FIMP + self.hand_dim]

    @property
    def penalty_wrench(self) -> np.ndarray:
        return self._st[S_FPEN:S_FPEN + self.hand_dim]

    @property
    def generalized_impulse(self) -> np.ndarray:
        """Jc^T p of the last step, configuration space (N s, N m s)."""
        return self._st[S_GIMP:S_GIMP + self.dof]

    kinetic_energy_j = ArrayFloat("_st", S_KE, doc="Proxy kinetic energy after the last step, J.")

    @property
    def collision_energy_j(self) -> tuple[float, float]:
        """Kinetic energy just before and just after the last step's collision impulse."""
        return float(self._st[S_KE_PRE]), float(self._st[S_KE_POST])

    contact_count = ArrayInt("_cnt", K_M, doc="Live contacts.")

    @property
    def proxy_state(self) -> str:
        return PROXY_STATE_NAMES[int(self._cnt[K_PROXY])]

    def counters(self) -> dict[str, int]:
        c = self._cnt
        return {
            "contacts": int(c[K_M]), "steps": int(c[K_STEPS]), "updates": int(c[K_UPDATES]),
            "dropped": int(c[K_DROPPED]), "collisions": int(c[K_COLLISIONS]),
            "nonfinite": int(c[K_NONFINITE]), "new": int(c[K_NEW]), "deformed": int(c[K_DEFORMED]),
            "left": int(c[K_LEFT]), "impending": int(c[K_N_IMPENDING]),
            "colliding": int(c[K_N_COLLIDING]), "penetrating": int(c[K_N_PENETRATING]),
            "separating": int(c[K_N_SEPARATING]), "rank": int(c[K_RANK]),
            "slipping": int(c[K_SLIPPING]), "flips_refused": int(c[K_FLIPS]), "flips_taken": int(c[K_FLIPS_TAKEN]),
            "rekeyed": int(c[K_REKEYED]),
            "recovering": int(c[K_RECOVERING]), "held": int(c[K_HELD]), "oscillating_steps": int(c[K_OSC_RUN]),
            "diverged": int(c[K_DIVERGED]),
        }

    def contacts(self) -> ContactSnapshot:
        m = int(self._cnt[K_M])
        C = self._C[:m].copy()
        CI = self._CI[:m].copy()
        return ContactSnapshot(
            keys=CI[:, CI_KEY:CI_KEY + 3], position_m=C[:, C_CP:C_CP + 3], normal=C[:, C_N:C_N + 3],
            separation_reported_m=C[:, C_D], v_constr_m_per_s=C[:, C_VC],
            local_point_body_m=C[:, C_P:C_P + 3], separation_m=C[:, C_S], separation_prev_m=C[:, C_SPREV],
            normal_velocity_m_per_s=C[:, C_VN], normal_force_n=C[:, C_FN],
            friction_force_n=C[:, C_FT:C_FT + 3], bristle_m=C[:, C_Z:C_Z + 3], impulse_n_s=C[:, C_IMP],
            state=[CONTACT_STATE_NAMES[s] for s in CI[:, CI_STATE]], slipping=CI[:, CI_SLIP].astype(bool),
            age_updates=CI[:, CI_AGE], deformation_m=C[:, C_DEF], recovered_m=C[:, C_REC],
        )

    def proxy_separations(self) -> np.ndarray:
        """Separation of the proxy at every live contact for the current pose and time (eq. 3),
        computed now (not the value of the last step). Not for the hot path."""
        m = int(self._cnt[K_M])
        out = np.empty(m)
        Rs, cs = self.link_poses()
        t = self.time_s
        for i in range(m):
            k = int(self._CI[i, CI_KEY])
            x = cs[k] + Rs[k] @ self._C[i, C_P:C_P + 3]
            n = self._C[i, C_N:C_N + 3]
            out[i] = (n @ (x - self._C[i, C_CP:C_CP + 3]) - self._C[i, C_VC] * (t - self._C[i, C_TU])
                      - self._C[i, C_REC])
        return out

    def pose_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """(R body-to-world 3x3, COM position world) of the proxy; a linkage: its root link's
        (R link-to-world, frame origin)."""
        if self.is_linkage:
            Rs, cs = self.link_poses()
            return Rs[0], cs[0]
        R = np.zeros((12, 12))
        c = np.zeros(3)
        _k._rigid_pose(self.kind, self._par, self._st, R, c)
        return R[:3, :3].copy(), c

    def link_poses(self, q=None) -> tuple[np.ndarray, np.ndarray]:
        """(R (L, 3, 3) link-to-world, frame origins (L, 3) world) of every link at the proxy's
        configuration, or at ``q``; a rigid tool is one link (its COM frame). Not for the hot path."""
        if not self.is_linkage:
            R, c = self.pose_matrix()
            return R[None], c[None]
        qv = self.q if q is None else np.ascontiguousarray(q, dtype=np.float64)
        lw = np.zeros_like(self._lw)
        _lk.forward_kinematics(self._lmeta, self._lk, self._lki, qv, lw)
        return lw[:, LW_R:LW_R + 9].reshape(-1, 3, 3).copy(), lw[:, LW_P:LW_P + 3].copy()

    def hand_state(self) -> np.ndarray:
        """Pose (7, x y z qw qx qy qz) and twist (6) of the hand point, world: a linkage's held
        link frame, a rigid tool's hand point. Not for the hot path."""
        out = np.zeros(13)
        if self.is_linkage:
            _lk.hand_state_linkage(self._lmeta, self._lk, self._lki, self._st, self._lw, out, 0)
            return out
        R, c = self.pose_matrix()
        r = R @ np.asarray(self.tool.hand_point_m, dtype=np.float64)
        qd = self.qd
        out[0:3] = c + r
        if self.kind == TOOL_PLANAR:
            th = float(self.q[2])
            out[3:7] = (math.cos(th / 2), 0.0, 0.0, math.sin(th / 2))
            w = np.array([0.0, 0.0, qd[2]])
            v = np.array([qd[0], qd[1], 0.0])
        elif self.kind == TOOL_SPATIAL:
            out[3:7] = self.q[3:7]
            w = qd[3:6].copy()
            v = qd[0:3].copy()
        else:
            out[3] = 1.0
            w = np.zeros(3)
            v = qd[0] * np.asarray(self.tool.axis, dtype=np.float64)
        out[7:10] = v + np.cross(w, r)
        out[10:13] = w
        return out

    def joint_state(self, hand_wrench_world) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """A linkage's ProxyState content: root frame pose (7) and twist (6), the hand wrench (6,
        world, at the held link's origin) as the wrench on the root frame origin (6) plus joint
        efforts (J), and the joint positions and rates (J). Not for the hot path."""
        if not self.is_linkage:
            raise ValueError("joint_state: only a linkage has joints")
        nj = len(self.tool.links) - 1
        out = (np.zeros(7), np.zeros(6), np.zeros(6), np.zeros(nj), np.zeros(nj), np.zeros(nj))
        self.joint_state_into(np.asarray(hand_wrench_world, dtype=np.float64), out)
        return out

    def joint_state_into(self, hand_wrench_world: np.ndarray, out, st=None, lw=None) -> None:
        """:meth:`joint_state` into ``out`` = (pose, twist, wrench, effort, joint positions, joint
        rates), float64 arrays of those sizes (the loop's, allocated at engagement); the hand
        wrench a float64 array of 6. For the step that acknowledges an update. ``st`` / ``lw``:
        copies of the model's state and link poses to read instead (the slot's ``ack_st`` /
        ``ack_lw``)."""
        pose, twist, wrench, effort, jq, jqd = out
        _lk.joint_state(self._lmeta, self._lk, self._lki, self._st if st is None else st,
                        self._lw if lw is None else lw, hand_wrench_world, pose, twist, wrench,
                        effort, jq, jqd, self._q_at + self.nq, S_QD + self.dof)

    # -- raw arrays (for the reference implementation and for tests) --------------------------
    def arrays(self):
        return self._par, self._st, self._C, self._CI, self._cnt

    def kernel_args(self):
        """``(kind, par, st, C, CI, cnt, wk)``: the arguments of ``kernels.step_rigid`` before the
        hand wrench, for callers that fuse the model step into their own kernel (the server loop)."""
        return self.kind, self._par, self._st, self._C, self._CI, self._cnt, self._wk

    @property
    def slot_address(self) -> int:
        """The address of the update slot's descriptor (``slot.slot_at``), for the tick's
        ``TK_UPD_DESC``."""
        return int(self._slot_desc.__array_interface__["data"][0])

    def linkage_args(self):
        """``(lmeta, lk, lki, lw)``: the linkage arrays ``linkage.step_linkage`` takes besides
        ``kernel_args`` (a linkage only)."""
        if not self.is_linkage:
            raise ValueError("linkage_args: not a linkage")
        return self._lmeta, self._lk, self._lki, self._lw


def linkage_arrays(tool: ToolSpec, velocity_terms: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lmeta, lk, lki) of a validated linkage ToolSpec (see ``layout``: LM_*, LK_*, LI_*);
    ``velocity_terms``: include the Coriolis / centripetal / gyroscopic terms (``LM_COR``)."""
    links = tool.links
    nl = len(links)
    d, h, _ = linkage_dims(nl, tool.planar)
    r = 3 if tool.planar else 6
    lmeta = np.zeros(NLM, dtype=np.int64)
    lmeta[LM_NLINKS] = nl
    lmeta[LM_PLANAR] = 1 if tool.planar else 0
    lmeta[LM_HELD] = int(tool.held_link)
    lmeta[LM_D] = d
    lmeta[LM_H] = h
    lmeta[LM_R] = r
    lmeta[LM_NQR] = 3 if tool.planar else 7
    lmeta[LM_COR] = 1 if velocity_terms else 0
    lk = np.zeros((nl, NLK))
    lki = np.zeros((nl, NLI), dtype=np.int64)
    for k, ln in enumerate(links):
        lk[k, LK_MASS] = float(ln.mass_kg)
        lk[k, LK_COM:LK_COM + 3] = np.asarray(ln.com_m, dtype=np.float64)
        lk[k, LK_I:LK_I + 9] = ln.inertia_matrix().ravel()
        axis = np.asarray(ln.axis, dtype=np.float64)
        quat = np.asarray(ln.origin_quat, dtype=np.float64)
        origin = np.asarray(ln.origin_m, dtype=np.float64)
        if ln.joint == "root":
            axis = np.array([0.0, 0.0, 1.0])  # unused: the root has no joint
        elif tool.planar:
            # exactly in the plane (the validation allowed rounding-sized deviations)
            axis = np.array([0.0, 0.0, math.copysign(1.0, axis[2])]) if ln.joint == "revolute" else \
                np.array([axis[0], axis[1], 0.0])
            quat = np.array([quat[0], 0.0, 0.0, quat[3]])
            origin = np.array([origin[0], origin[1], 0.0])
        lk[k, LK_AXIS:LK_AXIS + 3] = axis / np.linalg.norm(axis)
        lk[k, LK_OP:LK_OP + 3] = origin
        lk[k, LK_OR:LK_OR + 9] = quat_to_matrix(quat / np.linalg.norm(quat)).ravel()
        lki[k, LI_PARENT] = int(ln.parent)
        lki[k, LI_TYPE] = JOINT_TYPES[ln.joint]
        chain = list(range(r))
        j = k
        while j > 0:
            chain.append(r + j - 1)
            j = int(links[j].parent)
        chain.sort()
        lki[k, LI_NCHAIN] = len(chain)
        lki[k, LI_CHAIN:LI_CHAIN + len(chain)] = chain
    return lmeta, lk, lki


_WARM = False


def warm_up() -> None:
    """Load (or compile, first time on a machine) every kernel for every tool kind, once per
    process, on throw-away arrays: the first haptic step must not pay for it."""
    global _WARM
    if _WARM:
        return
    for kind in (TOOL_1DOF, TOOL_PLANAR, TOOL_SPATIAL):
        par = np.zeros(NPAR)
        par[P_DT] = 1e-3
        par[P_MASS] = 1.0
        par[P_INERTIA:P_INERTIA + 9] = np.eye(3).ravel()
        par[P_AXIS] = 1.0
        par[P_K] = 1000.0
        st = np.zeros(NSTATE)
        st[S_Q + 3] = 1.0
        cap = 2
        C = np.zeros((cap, NCOLS_F))
        CI = np.zeros((cap, NCOLS_I), dtype=np.int64)
        cnt = np.zeros(NCOUNT, dtype=np.int64)
        wk = np.zeros(_k.workspace_size(cap))
        keys = np.zeros((1, 3), dtype=np.int64)
        cp = np.zeros((1, 3))
        nrm = np.zeros((1, 3)); nrm[0, 0] = 1.0
        dsep = np.zeros(1); vc = np.zeros(1)
        sel = np.zeros(4, dtype=np.int64)
        # writable contact arrays (``update``'s copies) and read-only ones (the decoder's views
        # of a packet, which the server's loop hands over as they are)
        for contact_arrays in ((keys, cp, nrm, dsep, vc), frozen_copies(keys, cp, nrm, dsep, vc)):
            for use_qe in (0, 1):
                qe = np.zeros(7)
                qe[3] = 1.0
                _k.update_rigid(kind, par, st, C, CI, cnt, wk, *contact_arrays, 1, sel,
                                np.zeros((cap, NCOLS_F)), np.zeros((cap, NCOLS_I), dtype=np.int64),
                                qe, use_qe, np.zeros(NSTATE), np.zeros((3, 3)), np.zeros(3))
        st[S_QD] = -0.1
        _k.step_rigid(kind, par, st, C, CI, cnt, wk, np.zeros(6))
    # the linkage kernels (one compiled version serves planar and spatial linkages)
    for planar in (True, False):
        links = (LinkSpec(1.0, inertia_kg_m2=(1e-3, 1e-3, 1e-3)),
                 LinkSpec(1.0, (0.05, 0.0, 0.0), (1e-3, 1e-3, 1e-3), 0, "revolute", (0.0, 0.0, 1.0), (0.1, 0.0, 0.0)))
        m = LocalModel(ToolSpec.linkage(links, 1, planar), ContactParams(1000.0), period_s=1e-3, capacity=2,
                       warm=False)
        keys = np.array([[1, 1, 0]], dtype=np.int64)
        for tq in (None, m.q.copy()):
            m.update(keys, [[0.1, 0.0, 0.0]], [[1.0, 0.0, 0.0]], [0.0], tool_q=tq)
        m.reset(qd=np.r_[-0.1, np.zeros(m.dof - 1)])
        m.update(keys, [[0.1, 0.0, 0.0]], [[1.0, 0.0, 0.0]], [0.0])
        ro = frozen_copies(keys, np.array([[0.1, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]), np.zeros(1), np.zeros(1))
        for tq in (None, m.q.copy()):
            m.update_arrays(*ro, 1, tq)
        m.step(np.zeros(6))
        m.hand_state()
        m.joint_state(np.zeros(6))
    _WARM = True
