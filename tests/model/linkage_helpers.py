"""Linkages for the model tests: random trees, a planar 3-bar chain, and an analytic engine that
reports the chain's contacts with a wall and between its own links (from the proxy's pose); and
random contact normals a tool of each kind can feel (``random_normals``)."""
from __future__ import annotations

import math

import numpy as np

from hapticproxy.server.model import LinkSpec, ToolSpec

BAR_LENGTH_M = 0.06
BAR_WIDTH_M = 0.015
BAR_MASS_KG = 0.08
BAR_IZZ = BAR_MASS_KG * (BAR_LENGTH_M ** 2 + BAR_WIDTH_M ** 2) / 12.0


def random_normals(rng, n, kind):
    """``n`` random unit contact normals (n, 3) for a tool of ``kind``: in the x-y plane for
    "planar", +-x for "1dof", any direction otherwise."""
    nrm = rng.normal(size=(n, 3))
    if kind == "planar":
        nrm[:, 2] = 0.0
    if kind == "1dof":
        nrm[:] = 0.0
        nrm[:, 0] = rng.choice([-1.0, 1.0], n)
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    return nrm


def _random_inertia(rng, planar):
    if planar:
        return tuple(rng.uniform(1e-4, 1e-2, 3))
    A = rng.normal(size=(3, 3)) * 0.03
    return tuple(map(tuple, (A @ A.T + np.eye(3) * 1e-4).tolist()))


def _random_quat(rng, planar):
    if planar:
        a = rng.uniform(-math.pi, math.pi)
        return (math.cos(a / 2), 0.0, 0.0, math.sin(a / 2))
    q = rng.normal(size=4)
    return tuple(q / np.linalg.norm(q))


def random_linkage(rng, n_links: int, planar: bool, *, branching: bool = True, prismatic: bool = True) -> ToolSpec:
    """A random tree of ``n_links`` links (root first), joints revolute or prismatic."""
    links = [LinkSpec(float(rng.uniform(0.05, 1.0)), tuple(np.r_[rng.normal(size=2) * 0.03, 0.0 if planar else rng.normal() * 0.03]),
                      _random_inertia(rng, planar))]
    for k in range(1, n_links):
        parent = int(rng.integers(0, k)) if branching else k - 1
        joint = "prismatic" if prismatic and rng.random() < 0.3 else "revolute"
        if planar:
            if joint == "revolute":
                axis = (0.0, 0.0, float(rng.choice([-1.0, 1.0])))
            else:
                a = rng.uniform(-math.pi, math.pi)
                axis = (math.cos(a), math.sin(a), 0.0)
            origin = (float(rng.normal() * 0.05), float(rng.normal() * 0.05), 0.0)
            com = (float(rng.normal() * 0.03), float(rng.normal() * 0.03), 0.0)
        else:
            v = rng.normal(size=3)
            axis = tuple(v / np.linalg.norm(v))
            origin = tuple(rng.normal(size=3) * 0.05)
            com = tuple(rng.normal(size=3) * 0.03)
        links.append(LinkSpec(float(rng.uniform(0.05, 1.0)), com, _random_inertia(rng, planar), parent, joint, axis,
                              origin, _random_quat(rng, planar)))
    return ToolSpec.linkage(links, int(rng.integers(0, n_links)), planar)


def random_q(rng, tool: ToolSpec) -> np.ndarray:
    nj = len(tool.links) - 1
    joints = np.array([rng.uniform(-math.pi, math.pi) if ln.joint == "revolute" else rng.uniform(-0.05, 0.05)
                       for ln in tool.links[1:]])
    if tool.planar:
        return np.r_[rng.normal(size=2) * 0.05, rng.uniform(-math.pi, math.pi), joints]
    quat = rng.normal(size=4)
    return np.r_[rng.normal(size=3) * 0.05, quat / np.linalg.norm(quat), joints][: 7 + nj]


def bar_chain(n_links: int = 3, held_link: int | None = None, planar: bool = True) -> ToolSpec:
    """A chain of equal bars along their link x axes, each hinged about z at the end of the last
    (link frame at the bar's proximal end; the bar spans x in [0, L], y in [-w/2, w/2])."""
    izz = BAR_IZZ
    inertia = (izz * 0.1 if planar else BAR_MASS_KG * BAR_WIDTH_M ** 2 / 6.0, izz, izz)
    links = [LinkSpec(BAR_MASS_KG, (BAR_LENGTH_M / 2, 0.0, 0.0), inertia)]
    for k in range(1, n_links):
        links.append(LinkSpec(BAR_MASS_KG, (BAR_LENGTH_M / 2, 0.0, 0.0), inertia, k - 1, "revolute", (0.0, 0.0, 1.0),
                              (BAR_LENGTH_M, 0.0, 0.0)))
    return ToolSpec.linkage(links, n_links - 1 if held_link is None else held_link, planar)


def bar_corners(R, p) -> np.ndarray:
    """World corners (4 x 3) of a bar whose link frame is (R, p)."""
    local = np.array([[0.0, -BAR_WIDTH_M / 2, 0.0], [BAR_LENGTH_M, -BAR_WIDTH_M / 2, 0.0],
                      [BAR_LENGTH_M, BAR_WIDTH_M / 2, 0.0], [0.0, BAR_WIDTH_M / 2, 0.0]])
    return p + local @ R.T


def closest_on_bar(R, p, x):
    """(point on the bar's boundary, outward unit normal there towards x, signed distance) of world
    point x to the bar (negative inside: the shallowest face)."""
    lo = np.array([0.0, -BAR_WIDTH_M / 2])
    hi = np.array([BAR_LENGTH_M, BAR_WIDTH_M / 2])
    loc = (R.T @ (x - p))[:2]
    cl = np.clip(loc, lo, hi)
    if np.any(cl != loc):
        diff = loc - cl
        dist = float(np.linalg.norm(diff))
        n_loc = diff / dist
        point = cl
    else:
        depths = np.array([loc[0] - lo[0], hi[0] - loc[0], loc[1] - lo[1], hi[1] - loc[1]])
        f = int(np.argmin(depths))
        n_loc = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]][f])
        point = loc.copy()
        point[f // 2] = (lo if f % 2 == 0 else hi)[f // 2]
        dist = -float(depths[f])
    return p + R @ np.r_[point, 0.0], R @ np.r_[n_loc, 0.0], dist


def chain_contacts(model, *, wall_y=None, self_pairs=(), epsilon=0.005):
    """Contacts of the bar chain at the proxy's pose: bar corners against the wall y = wall_y
    (solid below, normal +y), and for each (a, b) in ``self_pairs`` the corners of a against
    bar b and of b against a. A self-contact is two contacts, one on each link (the paper's
    Fig. 11): a corner of a on a face of b is reported on a (vertex-face: c_p on b's face, n from
    b towards a) and on b (face-vertex: c_p at a's corner, -n, the same d)."""
    Rs, ps = model.link_poses()
    keys, cp, nrm, sep = [], [], [], []
    nl = len(Rs)
    if wall_y is not None:
        for k in range(nl):
            for i, c in enumerate(bar_corners(Rs[k], ps[k])):
                d = c[1] - wall_y
                if d <= epsilon:
                    keys.append((k, 1, i)); cp.append((c[0], wall_y, 0.0)); nrm.append((0.0, 1.0, 0.0)); sep.append(d)
    for a, b in self_pairs:
        for owner, other in ((a, b), (b, a)):
            for i, c in enumerate(bar_corners(Rs[owner], ps[owner])):
                point, n, d = closest_on_bar(Rs[other], ps[other], c)
                if d <= epsilon:
                    keys.append((owner, 100 + other, i)); cp.append(point); nrm.append(n); sep.append(d)
                    keys.append((other, 100 + owner, 10 + i)); cp.append(c); nrm.append(-n); sep.append(d)
    n = len(keys)
    return (np.array(keys, dtype=np.int64).reshape(n, 3), np.array(cp, float).reshape(n, 3),
            np.array(nrm, float).reshape(n, 3), np.array(sep, float), np.zeros(n))
