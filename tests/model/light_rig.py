"""A tool resting on a floor under a pushing hand, in simulated time, at the model level: the
``LocalModel``, the controller kernel (``control.haptic_step`` / ``haptic_step_linkage``, as the
loop calls it), the simulated device (the ``sim`` driver, its hand a constant push) and an
analytic engine: the floor y = 0 (normal +y) under a box tool, or under a chain of bars for a
linkage, reported to the model at 60 Hz from the proxy's pose (the engine's tool follows the
proxy and stops at the floor, as a rigid engine's does).

``rest_on_floor(...)`` runs it and returns the proxy's speeds and the force on the hand over the
last part of the run (``RestResult``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hapticproxy.server import config as cfg
from hapticproxy.server import control as ctl
from hapticproxy.server.devices.base import empty_state
from hapticproxy.server.devices.sim import make_sim_device
from hapticproxy.server.model import ContactParams, LinkSpec, LocalModel, ToolSpec

#: rigid kinds, and a linkage on a planar or a spatial device
KINDS = ("1dof", "planar", "spatial", "linkage-planar", "linkage-spatial")
BAR_LENGTH_M = 0.06
BAR_WIDTH_M = 0.015
ENGINE_RATE_HZ = 60.0
EPSILON_M = 0.005


def box_inertia(mass_kg: float, size_m) -> tuple[float, float, float]:
    """Principal moments of a uniform box of full sizes (x, y, z)."""
    a, b, c = size_m
    return (mass_kg * (b * b + c * c) / 12, mass_kg * (a * a + c * c) / 12, mass_kg * (a * a + b * b) / 12)


def chain_tool(link_mass_kg: float, link_izz_kg_m2: float, planar: bool, n_links: int = 3,
               held_link: int = 1) -> ToolSpec:
    """A chain of bars (``BAR_LENGTH_M`` along each link's x, hinged about z at the end of the
    last; link frame at the bar's proximal end), each ``link_mass_kg`` with I_zz
    ``link_izz_kg_m2`` about its COM (its other moments in proportion to a bar's)."""
    izz = float(link_izz_kg_m2)
    ixx = izz * BAR_WIDTH_M ** 2 / (BAR_LENGTH_M ** 2 + BAR_WIDTH_M ** 2) * 2
    inertia = (ixx, izz, izz)
    links = [LinkSpec(link_mass_kg, (BAR_LENGTH_M / 2, 0.0, 0.0), inertia)]
    for k in range(1, n_links):
        links.append(LinkSpec(link_mass_kg, (BAR_LENGTH_M / 2, 0.0, 0.0), inertia, k - 1, "revolute",
                              (0.0, 0.0, 1.0), (BAR_LENGTH_M, 0.0, 0.0)))
    return ToolSpec.linkage(links, held_link, planar)


@dataclass
class RestResult:
    """What a run did. Speeds are maxima over the last ``window_s`` of the run: ``linear_m_per_s``
    (the proxy's COM / root origin, world), ``angular_rad_per_s`` (rotation; for a linkage also
    its joint rates); ``cmd_n``: the mean force on the hand along the push over the window (the
    device's command), ``cmd_spread_n`` its range; ``push_n`` the hand's push; ``finite``: every
    value stayed finite and nothing faulted."""

    linear_m_per_s: float
    angular_rad_per_s: float
    cmd_n: float
    cmd_spread_n: float
    push_n: float
    finite: bool
    model: LocalModel
    qd: np.ndarray = field(repr=False)
    cmd: np.ndarray = field(repr=False)
    counters: dict = field(default_factory=dict)
    rc: int = 0

    @property
    def at_rest(self) -> bool:
        return self.finite and self.linear_m_per_s < 1e-3 and self.angular_rad_per_s < 1e-3

    @property
    def balanced(self) -> bool:
        """The force on the hand balances the push within 2 %, and stays within that."""
        return (self.finite and abs(self.cmd_n - self.push_n) <= 0.02 * self.push_n
                and self.cmd_spread_n <= 0.02 * self.push_n)


class _Floor:
    """The analytic engine: which tool points report contacts with the floor y = 0."""

    def __init__(self, kind: str, half_m, model: LocalModel, engine_frame: bool = True) -> None:
        self.kind = kind
        self.engine_frame = engine_frame
        self.model = model
        hx, hy, hz = half_m
        if kind == "1dof":
            self.body = np.array([[0.0, -hy, 0.0]])
        elif kind == "planar":
            self.body = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0]])
        elif kind == "spatial":
            self.body = np.array([[sx * hx, -hy, sz * hz] for sx in (-1, 1) for sz in (-1, 1)])
        else:  # a chain: each bar's 4 (planar) corners; spatial adds +-z faces of the bars
            w = BAR_WIDTH_M / 2
            pts = [[0.0, -w, 0.0], [BAR_LENGTH_M, -w, 0.0], [BAR_LENGTH_M, w, 0.0], [0.0, w, 0.0]]
            if kind == "linkage-spatial":
                pts = [[x, y, s * w] for x, y, _ in pts for s in (-1, 1)]
            self.body = np.array(pts)

    def update(self) -> None:
        m = self.model
        q = m.q.copy()
        Rs, cs = m.link_poses(q)
        # the engine's tool follows the proxy and stops at the floor (lifted out of it)
        low = min(float(np.min(cs[k][1] + self.body @ Rs[k].T[:, 1])) for k in range(len(Rs)))
        if low < 0.0:
            if self.kind == "1dof":
                q[0] -= low
            elif self.kind.startswith("linkage") or self.kind in ("planar", "spatial"):
                q[1] -= low
            Rs, cs = m.link_poses(q)
        keys, cp, nrm, sep = [], [], [], []
        for k in range(len(Rs)):
            for i, p in enumerate(cs[k] + self.body @ Rs[k].T):
                if p[1] <= EPSILON_M:
                    keys.append((k, 1, i))
                    cp.append((p[0], 0.0, p[2]))
                    nrm.append((0.0, 1.0, 0.0))
                    sep.append(p[1])
        n = len(keys)
        m.update(np.array(keys, dtype=np.int64).reshape(n, 3), np.array(cp, float).reshape(n, 3),
                 np.array(nrm, float).reshape(n, 3), np.array(sep, float), np.zeros(n), tool_q=q if self.engine_frame else None)


def rest_on_floor(kind: str, mass_kg: float, inertia_kg_m2=None, *, rate_hz: float = 1000.0,
                  push_n: float = 1.0, size_m=(0.04, 0.04, 0.04), seconds: float = 1.0, window_s: float = 0.3,
                  controller: dict | None = None, contact: dict | None = None, gap_m: float = 0.001,
                  qd0=None, model_kw: dict | None = None, build=None, engine_frame: bool = True,
                  device_cfg: dict | None = None, fit: bool = True, passivity: dict | None = None) -> RestResult:
    """Put a tool of ``kind`` (``KINDS``) ``gap_m`` above the floor, the hand pushing its device
    down with ``push_n``, and run ``seconds`` of simulated time.

    Rigid tools are boxes of full ``size_m`` with principal moments ``inertia_kg_m2`` (3; None:
    the box's); a linkage is ``chain_tool`` with ``mass_kg`` and I_zz ``inertia_kg_m2`` per link,
    lying straight on the floor, the hand on its middle link. ``controller`` / ``contact``: config
    keys of ``[controller]`` / ``[model]``. ``qd0``: the proxy's initial velocity. ``build``:
    ``build(tool, contact_params, period_s)`` returns the LocalModel (default: as the server's
    ``ModelFactory`` does, with these keys). ``fit``: the coupling's damping for the tool as the
    loop sets it at engagement (``Controller.fit_tool``); False keeps the configured one.
    ``passivity``: config keys of ``[passivity]`` (the layer at its defaults if None)."""
    model_keys = dict(contact or {})
    settings = cfg.load({"loop": {"rate_hz": rate_hz}, "controller": dict(controller or {}),
                         "model": model_keys, "safety": {"allow_outside_stable_region": True},
                         "device": {"driver": "sim", "kind": _device_kind(kind)},
                         "passivity": dict(passivity or {})})
    mc = settings["model"]
    cparams = ContactParams(mc["stiffness_n_per_m"], mc["damping_n_s_per_m"], mc["restitution"], mc["mu_static"],
                            mc["mu_kinetic"])
    dt = 1.0 / rate_hz
    half = tuple(0.5 * s for s in size_m)
    if kind.startswith("linkage"):
        tool = chain_tool(mass_kg, inertia_kg_m2 if inertia_kg_m2 is not None else
                          mass_kg * (BAR_LENGTH_M ** 2 + BAR_WIDTH_M ** 2) / 12, kind == "linkage-planar")
    else:
        moments = box_inertia(mass_kg, size_m) if inertia_kg_m2 is None else tuple(np.broadcast_to(inertia_kg_m2, 3))
        if kind == "1dof":
            tool = ToolSpec.one_dof(mass_kg, axis=(0.0, 1.0, 0.0))
        elif kind == "planar":
            tool = ToolSpec.planar(mass_kg, moments[2])
        else:
            tool = ToolSpec.spatial(mass_kg, moments)
    kw = dict(model_kw or {})
    if kind.startswith("linkage"):
        # without weight a bar that the hand does not hold is free to turn about its joint while
        # its far end lifts off the floor (neutrally stable): a weight of a tenth of the push
        # keeps the chain down (at most the earth's gravity)
        g = min(9.81, 0.1 * push_n / (mass_kg * len(tool.links)))
        kw.setdefault("gravity_m_per_s2", (0.0, -g, 0.0))
    if build is None:
        m = LocalModel(tool, cparams, period_s=dt, policy=mc["policy"], epsilon_m=EPSILON_M, capacity=32,
                       recovery_speed_m_per_s=mc["recovery_speed_m_per_s"], **kw)
    else:
        m = build(tool, cparams, dt)
    # the proxy above the floor, at rest (or at qd0)
    if kind == "1dof":
        q = [half[1] + gap_m]
    elif kind == "planar":
        q = [0.0, half[1] + gap_m, 0.0]
    elif kind == "spatial":
        q = [0.0, half[1] + gap_m, 0.0, 1.0, 0.0, 0.0, 0.0]
    else:
        q = [-BAR_LENGTH_M * 1.5, BAR_WIDTH_M / 2 + gap_m] + ([0.0] if kind == "linkage-planar" else [0.0, 1, 0, 0, 0])
        q += [0.0] * (len(tool.links) - 1)
    m.reset(q, qd0)
    floor = _Floor(kind, half, m, engine_frame)
    dkind = _device_kind(kind)
    push = {"1dof": [-push_n], "planar": [0.0, -push_n, 0.0], "spatial": [0.0, -push_n, 0.0, 0.0, 0.0, 0.0]}[dkind]
    dev_cfg = {"kind": dkind, "hand": {"type": "constant", "wrench": push, "start": "server"}, **(device_cfg or {})}
    if dkind == "1dof":
        dev_cfg["axis"] = [0.0, 1.0, 0.0]
    device = make_sim_device(dev_cfg, period_s=dt, clock_ns=lambda: 0)
    c = ctl.Controller(settings, dkind, device.limits)
    # as the loop does (HapticLoop's build, its engagement): the device's figures, then the
    # coupling's damping for this tool (a heavy one's raised: control.Controller.fit_tool)
    c.set_moving_figures(device.info)
    if fit:
        c.fit_tool(tool)
    device.enable()
    row = empty_state()
    device.read(row)
    hs = m.hand_state()
    c.set_offset(*ctl.index_offset(dkind, row[:7], hs[:7], (0.0, 1.0, 0.0), (0.0, 1.0, 0.0)))
    c.cs[ctl.CS_GAIN] = c.cs[ctl.CS_TARGET] = 1.0   # rendered in full from the first step
    n = int(round(seconds * rate_hz))
    upd_every = max(1, int(round(rate_hz / ENGINE_RATE_HZ)))
    qds = np.zeros((n, m.dof))
    cmds = np.zeros((n, 6))
    finite = True
    rc = 0
    linkage = m.is_linkage
    if linkage:
        par, st, C, CI, cnt = m.arrays()
        _, _, _, _, _, _, wk = m.kernel_args()
        lmeta, lk, lki, lw = m.linkage_args()
    else:
        kargs = m.kernel_args()
    for i in range(n):
        if i % upd_every == 0:
            floor.update()
        device.read(row)
        if linkage:
            rc = ctl.haptic_step_linkage(c.cp, c.cs, c.cc, row, c.cmd, par, lmeta, lk, lki, st, C, CI, cnt, wk, lw,
                                         c.hand)
        else:
            rc = ctl.haptic_step(c.cp, c.cs, c.cc, row, c.cmd, 1, *kargs, c.hand, c.R, c.c)
        if rc == ctl.RC_DIVERGED:
            # the loop fades here (lifecycle.FAULT_POLICY); the rig has no lifecycle and renders on
            # in full, so a test sees the integration itself (the counters say it was flagged)
            c.cs[ctl.CS_TARGET] = 1.0
            rc = 0
        device.write(c.cmd)
        qds[i] = m.qd
        cmds[i] = c.cmd
        if rc != 0 or not np.all(np.isfinite(m.qd)):
            finite = False
            qds = qds[:i + 1]
            cmds = cmds[:i + 1]
            break
    w0 = max(0, len(qds) - int(round(window_s * rate_hz)))
    lin, ang = _speeds(kind, m, qds[w0:])
    along = cmds[w0:, 1]
    finite = finite and m.counters()["nonfinite"] == 0
    return RestResult(lin, ang, float(np.mean(along)) if len(along) else math.nan,
                      float(np.ptp(along)) if len(along) else math.inf, float(push_n), finite, m, qds, cmds,
                      m.counters(), int(rc))


def _device_kind(kind: str) -> str:
    return {"linkage-planar": "planar", "linkage-spatial": "spatial"}.get(kind, kind)


def _speeds(kind: str, m: LocalModel, qd: np.ndarray) -> tuple[float, float]:
    if len(qd) == 0:
        return math.inf, math.inf
    a = np.abs(qd)
    if kind == "1dof":
        return float(a[:, 0].max()), 0.0
    if kind in ("planar", "linkage-planar"):
        lin, rot = a[:, :2], a[:, 2:]
    else:
        lin, rot = a[:, :3], a[:, 3:]
    return float(lin.max()), float(rot.max())
