"""A linkage environment client for the server-loop tests in simulated time: a planar chain of
bars (link frame at a bar's proximal end, the bar along +x) whose links touch a floor y = wall_y
(solid below). It speaks the real protocol over the in-memory transport: its Hello carries the
links and the held link; it follows the newest ProxyState (root pose + joint positions) and
reports every bar corner within epsilon of the floor, keyed (link, 1, corner)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hapticproxy.protocol.codec import Hello
from hapticproxy.protocol.messages import ToolKind
from server_harness import ProtocolEnv, contact_arrays

BAR_L = 0.06
BAR_W = 0.015
BAR_M = 0.08
BAR_IZZ = BAR_M * (BAR_L ** 2 + BAR_W ** 2) / 12.0


def bar_links(n: int) -> list[dict]:
    inertia = [BAR_M * BAR_W ** 2 / 6.0, BAR_IZZ, BAR_IZZ, 0.0, 0.0, 0.0]
    links = [dict(mass_kg=BAR_M, com_m=[BAR_L / 2, 0.0, 0.0], inertia_kg_m2=inertia, parent=-1, joint_type=0,
                  joint_axis=[0.0, 0.0, 1.0], joint_origin=[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])]
    for k in range(1, n):
        links.append(dict(mass_kg=BAR_M, com_m=[BAR_L / 2, 0.0, 0.0], inertia_kg_m2=inertia, parent=k - 1,
                          joint_type=1, joint_axis=[0.0, 0.0, 1.0],
                          joint_origin=[BAR_L, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
    return links


def chain_frames(root_xy_theta, joints):
    """(R (L, 2, 2), origins (L, 2)) of the bars of a planar chain (all joints revolute about +z)."""
    x, y, th = root_xy_theta
    Rs, ps = [], []
    p = np.array([x, y])
    for k in range(len(joints) + 1):
        if k:
            p = p + BAR_L * np.array([math.cos(th), math.sin(th)])
            th = th + joints[k - 1]
        Rs.append(np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]))
        ps.append(p.copy())
    return Rs, ps


def corners(R, p):
    local = np.array([[0.0, -BAR_W / 2], [BAR_L, -BAR_W / 2], [BAR_L, BAR_W / 2], [0.0, BAR_W / 2]])
    return p + local @ R.T


@dataclass(frozen=True)
class LinkageParams:
    """A :class:`LinkageWallEnv`'s chain, floor and engine. ``held_link`` None: the last bar;
    ``start``: the root's (x, y, theta); ``joints`` None: a straight chain; ``rigid``: the engine's
    chain cannot enter the floor (it is lifted out, as a rigid engine would hold it), so it lags
    the proxy when the proxy presses in; ``send_joints``: report the engine's joint positions in
    every ContactUpdate (minor 1)."""

    n_links: int = 3
    held_link: int | None = None
    wall_y: float = 0.0
    epsilon: float = 0.005
    rate_hz: float = 60.0
    start: tuple[float, float, float] = (-0.09, 0.03, 0.0)
    joints: tuple[float, ...] | None = None
    rigid: bool = False
    send_joints: bool = True

    def hello(self) -> Hello:
        n = self.n_links
        return Hello(client_nonce=1, engine="linkage-env", tool_kind=ToolKind.LINKAGE, mass_kg=BAR_M * n,
                     max_contacts=32, epsilon_m=self.epsilon, env_rate_hz=self.rate_hz, links=bar_links(n),
                     held_link=n - 1 if self.held_link is None else self.held_link)


class LinkageWallEnv(ProtocolEnv):
    """See the module docstring; ``params``: the keywords of :class:`LinkageParams`."""

    def __init__(self, url, clock, **params):
        p = self.params = LinkageParams(**params)
        self.root = np.array(p.start, dtype=float)
        self.joints = np.zeros(p.n_links - 1) if p.joints is None else np.array(p.joints, dtype=float)
        super().__init__(url, clock, p.hello())

    def pose7(self):
        x, y, th = self.root
        return np.array([x, y, 0.0, math.cos(th / 2), 0.0, 0.0, math.sin(th / 2)])

    def _lift_out_of_the_floor(self):
        Rs, ps = chain_frames(self.root, self.joints)
        low = min(corners(R, p)[:, 1].min() for R, p in zip(Rs, ps))
        if low < self.params.wall_y:
            self.root[1] += self.params.wall_y - low

    def contacts(self):
        Rs, ps = chain_frames(self.root, self.joints)
        keys, pos, nor, sep = [], [], [], []
        for k, (R, p) in enumerate(zip(Rs, ps)):
            for i, c in enumerate(corners(R, p)):
                d = c[1] - self.params.wall_y
                if d <= self.params.epsilon:
                    keys.append((k, 1, i)); pos.append((c[0], self.params.wall_y, 0.0)); nor.append((0.0, 1.0, 0.0))
                    sep.append(d)
        return contact_arrays(keys, pos, nor, sep)

    def _follow(self, ps):
        pose = ps.proxy_pose
        self.root = np.array([pose[0], pose[1], 2 * math.atan2(pose[6], pose[3])])
        self.joints = np.array(ps.joint_position, dtype=float)
        if self.params.rigid:
            self._lift_out_of_the_floor()

    def _send(self, now):
        k, p, n, d, v = self.contacts()
        extra = {"tool_joint_position": self.joints} if self.params.send_joints else {}
        self.ep.send_contacts(now, now * 1e-9, self.pose7(), k, p, n, d, v, **extra)

    def _next_ns(self, now):
        return now + int(1e9 / self.params.rate_hz)
