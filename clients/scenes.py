"""The planar scenes, engine-neutral: the paper's testbed (its Fig. 12) and friends, in SI units.

Both the stub and the pymunk engine build their worlds from these descriptions, so the same scene
name means the same geometry in both (the pymunk engine turns a half-plane into a thick slab).

World frame: the device's plane is the world x-y plane, rotation about +z. **+y points towards the
bottom of the paper's Fig. 12** (the paper pushes the tool "towards the bottom-most wall" with
F = (0, +0.5 N)), and there is no gravity: the paper's device is a horizontal planar device, so
gravity never acts in its plane.

The paper gives only two numbers of its testbed (the bottom wall is met at y_COM = 124 mm; the peg,
rotated 90 deg, fits the bottom hole exactly). The rest are this project's choices:

- tool (the peg): a 80 mm x 20 mm rectangle, 0.25 kg (uniform: Izz = m (a^2 + b^2) / 12 =
  1.417e-4 kg m^2), tool frame at its centre (= centre of mass), long side along the tool x axis;
  starts at the origin, unrotated.
- enclosure: inner walls at x = -200 mm and x = +200 mm and y = -100 mm (top); the bottom wall's
  top face is at y = 134 mm, so the unrotated peg (half height 10 mm) touches it with its centre at
  y = 124 mm, the paper's figure.
- bottom hole: centred at x = 0, 20 mm wide (exactly the peg's width) and 40 mm deep (bottom at
  y = 174 mm). The peg rotated by 90 deg and pushed in touches both side walls and the bottom with
  its centre at (0, 134 mm).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

#: The peg: length along the tool x axis, width along the tool y axis [m], mass [kg].
TOOL_LENGTH_M = 0.080
TOOL_WIDTH_M = 0.020
TOOL_MASS_KG = 0.25
TOOL_IZZ_KG_M2 = TOOL_MASS_KG * (TOOL_LENGTH_M ** 2 + TOOL_WIDTH_M ** 2) / 12.0

ENCLOSURE_LEFT_M = -0.200
ENCLOSURE_RIGHT_M = 0.200
ENCLOSURE_TOP_M = -0.100
BOTTOM_WALL_Y_M = 0.134  # top face of the bottom wall: the unrotated peg touches it at y_COM = 124 mm
WALL_CONTACT_Y_COM_M = BOTTOM_WALL_Y_M - TOOL_WIDTH_M / 2  # 0.124, the paper's Fig. 14 figure
HOLE_CENTRE_X_M = 0.0
HOLE_WIDTH_M = TOOL_WIDTH_M  # fits the peg exactly
HOLE_DEPTH_M = 0.040
HOLE_BOTTOM_Y_M = BOTTOM_WALL_Y_M + HOLE_DEPTH_M  # 0.174
#: Pose (x, y, angle) of the peg resting in the hole: rotated 90 deg, touching sides and bottom.
IN_HOLE_POSE = (HOLE_CENTRE_X_M, HOLE_BOTTOM_Y_M - TOOL_LENGTH_M / 2, math.pi / 2)

#: The ``linkage`` scene's tool (issue 6; our choice): a planar chain of LINK_COUNT equal bars
#: joined end to end by pivots (revolute about +z), held by its last link. A link's frame is at
#: its proximal pivot, the bar spanning x in [0, L] and y in [-W/2, W/2] of that frame; the next
#: link's pivot is at (L, 0). The bar's COM is at (L/2, 0); uniform: Izz = m (L^2 + W^2) / 12.
LINK_COUNT = 3
LINK_LENGTH_M = 0.070
LINK_WIDTH_M = 0.016
LINK_MASS_KG = 0.15
LINK_IZZ_KG_M2 = LINK_MASS_KG * (LINK_LENGTH_M ** 2 + LINK_WIDTH_M ** 2) / 12.0
#: the root link's frame at the start: the straight chain centred on the origin
LINKAGE_START = (-1.5 * LINK_LENGTH_M, 0.0, 0.0)


@dataclass(frozen=True)
class HalfPlane:
    """Solid on the side opposite ``normal``: points p with ``normal . (p - point) < 0`` are inside.
    ``normal`` (unit) points from the solid into free space (towards the tool)."""

    name: str
    point: tuple[float, float]
    normal: tuple[float, float]
    #: (amplitude [m], frequency [Hz]): the plane oscillates along its normal as
    #: ``point + normal * amplitude * sin(2 pi f t)`` (a moving constraint, for v_constr)
    oscillation: tuple[float, float] | None = None


@dataclass(frozen=True)
class Box:
    """A rectangle: centre (x, y) [m], full size (w, h) [m], angle [rad]; static if ``mass_kg`` is None."""

    name: str
    centre: tuple[float, float]
    size: tuple[float, float]
    angle: float = 0.0
    mass_kg: float | None = None

    def vertices(self) -> list[tuple[float, float]]:
        """World vertices, counter-clockwise (x right, y up in the maths sense)."""
        c, s = math.cos(self.angle), math.sin(self.angle)
        a, b = self.size[0] / 2, self.size[1] / 2
        out = []
        for lx, ly in ((-a, -b), (a, -b), (a, b), (-a, b)):
            out.append((self.centre[0] + c * lx - s * ly, self.centre[1] + s * lx + c * ly))
        return out


@dataclass(frozen=True)
class PlanarScene:
    name: str
    description: str
    obstacles: tuple = ()
    tool_start: tuple[float, float, float] = (0.0, 0.0, 0.0)  # x, y [m], angle [rad]
    facts: dict = field(default_factory=dict)


def _enclosure(with_hole: bool) -> tuple:
    wall = [
        HalfPlane("top wall", (0.0, ENCLOSURE_TOP_M), (0.0, 1.0)),
        HalfPlane("left wall", (ENCLOSURE_LEFT_M, 0.0), (1.0, 0.0)),
        HalfPlane("right wall", (ENCLOSURE_RIGHT_M, 0.0), (-1.0, 0.0)),
    ]
    if not with_hole:
        return tuple(wall + [HalfPlane("bottom wall", (0.0, BOTTOM_WALL_Y_M), (0.0, -1.0))])
    h = HOLE_DEPTH_M
    left_w = (HOLE_CENTRE_X_M - HOLE_WIDTH_M / 2) - ENCLOSURE_LEFT_M
    right_w = ENCLOSURE_RIGHT_M - (HOLE_CENTRE_X_M + HOLE_WIDTH_M / 2)
    return tuple(wall + [
        Box("bottom wall, left of the hole", (ENCLOSURE_LEFT_M + left_w / 2, BOTTOM_WALL_Y_M + h / 2), (left_w, h)),
        Box("bottom wall, right of the hole", (ENCLOSURE_RIGHT_M - right_w / 2, BOTTOM_WALL_Y_M + h / 2), (right_w, h)),
        HalfPlane("hole bottom", (0.0, HOLE_BOTTOM_Y_M), (0.0, -1.0)),
    ])


_COMMON_FACTS = {
    "tool_size_m": (TOOL_LENGTH_M, TOOL_WIDTH_M),
    "tool_mass_kg": TOOL_MASS_KG,
    "tool_izz_kg_m2": TOOL_IZZ_KG_M2,
    "frame": "+y towards the bottom of the paper's Fig. 12; no gravity (horizontal device)",
}

SCENES: dict[str, PlanarScene] = {
    "testbed": PlanarScene(
        "testbed",
        "the paper's Fig. 12: rigid enclosure, a tight 20 mm x 40 mm hole in the bottom wall, the peg at the origin",
        _enclosure(with_hole=True),
        facts={**_COMMON_FACTS, "enclosure_x_m": (ENCLOSURE_LEFT_M, ENCLOSURE_RIGHT_M), "enclosure_top_y_m": ENCLOSURE_TOP_M,
               "bottom_wall_y_m": BOTTOM_WALL_Y_M, "wall_contact_y_com_m": WALL_CONTACT_Y_COM_M,
               "hole_x_m": (HOLE_CENTRE_X_M - HOLE_WIDTH_M / 2, HOLE_CENTRE_X_M + HOLE_WIDTH_M / 2),
               "hole_bottom_y_m": HOLE_BOTTOM_Y_M},
    ),
    "hole": PlanarScene(
        "hole",
        "the testbed with the peg already rotated 90 deg and resting in the bottom hole (Figs. 16/17 start)",
        _enclosure(with_hole=True),
        tool_start=IN_HOLE_POSE,
        facts={**_COMMON_FACTS, "in_hole_pose": IN_HOLE_POSE, "hole_bottom_y_m": HOLE_BOTTOM_Y_M},
    ),
    "wall": PlanarScene(
        "wall",
        "the Fig. 14 wall alone: solid for y >= 134 mm, the peg at the origin (touches it at y_COM = 124 mm)",
        (HalfPlane("bottom wall", (0.0, BOTTOM_WALL_Y_M), (0.0, -1.0)),),
        facts={**_COMMON_FACTS, "bottom_wall_y_m": BOTTOM_WALL_Y_M, "wall_contact_y_com_m": WALL_CONTACT_Y_COM_M},
    ),
    "push": PlanarScene(
        "push",
        "closed enclosure (no hole) with three movable boxes the peg can push",
        _enclosure(with_hole=False) + (
            Box("box A", (0.0, 0.060), (0.040, 0.040), 0.0, 0.10),
            Box("box B", (0.100, 0.050), (0.060, 0.030), 0.3, 0.15),
            Box("box C", (-0.110, 0.080), (0.030, 0.030), 0.0, 0.05),
        ),
        facts={**_COMMON_FACTS, "movable": "box A 40x40 mm 0.10 kg at (0, 60 mm); box B 60x30 mm 0.15 kg at "
                                            "(100, 50) mm, 0.3 rad; box C 30x30 mm 0.05 kg at (-110, 80) mm"},
    ),
    "linkage": PlanarScene(
        "linkage",
        "the testbed with a 3-bar planar linkage (pivot joints) as the tool, held by its last link",
        _enclosure(with_hole=True),
        tool_start=LINKAGE_START,
        facts={"links": LINK_COUNT, "link_size_m": (LINK_LENGTH_M, LINK_WIDTH_M), "link_mass_kg": LINK_MASS_KG,
               "link_izz_kg_m2": LINK_IZZ_KG_M2, "held_link": LINK_COUNT - 1,
               "frame": _COMMON_FACTS["frame"], "bottom_wall_y_m": BOTTOM_WALL_Y_M,
               "hole_x_m": (HOLE_CENTRE_X_M - HOLE_WIDTH_M / 2, HOLE_CENTRE_X_M + HOLE_WIDTH_M / 2)},
    ),
    "piston": PlanarScene(
        "piston",
        "the Fig. 14 wall moving along its normal: 20 mm amplitude at 0.5 Hz (a moving constraint)",
        (HalfPlane("moving wall", (0.0, BOTTOM_WALL_Y_M), (0.0, -1.0), oscillation=(0.020, 0.5)),),
        facts={**_COMMON_FACTS, "wall_y_m": f"{BOTTOM_WALL_Y_M} - 0.020 sin(pi t)"},
    ),
}


def scene(name: str, available: tuple[str, ...]) -> PlanarScene:
    """The scene ``name`` if the calling engine offers it, else ``ValueError`` naming the choices."""
    if name not in available:
        raise ValueError(f"unknown scene {name!r}; choose one of: {', '.join(available)}")
    return SCENES[name]
