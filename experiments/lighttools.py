"""Light tools (issue 31, item 1's measure): tools from 5 g to 2 kg with moments down to 1e-7 kg m^2,
of every kind, resting on a floor under a pushing hand, through the whole server in simulated time.

The rig (one process, ``SimClock``): ``HapticLoop`` as ``hapticproxy serve`` builds it (its config's
controller, model and safety defaults) on the simulated device of the tool's kind (a linkage on the
planar or spatial device) whose hand is a pure force: a constant push of ``PUSH_N`` down (-y), no
mass or damping of its own (``hand = {type = "constant"}``). The environment is an engine behind
the real protocol over the ``mem://`` transport (:class:`FloorEnv`): its Hello declares the tool
(mass, principal moments; a linkage's links), it follows each ProxyState (pose, joints), stops its
tool at the floor y = 0 as a rigid engine does, and at ``ENGINE_RATE_HZ`` reports every corner of
its tool within ``EPSILON_M`` of the floor (normal +y), in its own tool frame. The tool starts
``GAP_M`` above the floor, so the proxy lands on it under the push. The floor has friction
(``MU_STATIC``, ``MU_KINETIC``: the server's ``[model]`` keys; see there why).

The tools (:func:`grid`): the rigid kinds are a 40 mm box (geometry: one bottom point for the 1dof
tool, two bottom corners for the planar, four for the spatial); their declared moments are
isotropic, ``I`` each. A linkage is a chain of ``LINKS`` bars of 60 x 15 mm hinged about z, lying
flat, the hand on the middle bar; the tool's mass is split equally over its links and ``I`` is each
link's moment about z (the others in a bar's proportion). ``I`` runs over the decades from
``INERTIA_MIN_KG_M2`` up to a plausible moment for the mass (a 150 mm rod of that mass about its
middle; a 60 x 15 mm bar of the link's mass for a linkage), that moment included. A linkage's free
bars are held down by a weight of a tenth of the push (``[model] gravity_m_per_s2``): without any,
a bar hinged to the held one is neutrally stable (its far end free to lift).

Each run lasts ``SETTLE_S`` + ``WINDOW_S`` of simulated time (``SETTLE_HEAVY_S`` for tools of 1 kg and
more: a heavy tool on the default coupling takes seconds, not one); over the last ``WINDOW_S`` it
records the proxy's largest linear speed (m/s: the COM or the root's origin) and angular speed
(rad/s: every rotational coordinate of the model's velocity, a linkage's joint rates included)
and the largest |F - push| of the force the device renders along the push. A run passes
(:func:`verdict`) if the Hello was accepted, nothing faulted, every ProxyState of the window said
``engaged``, both speeds stay below ``TWIST_MAX`` and |F - push| below ``BALANCE_MAX`` x push; a
Hello the server refuses is reported with its reason (the issue's other outcome).

Each rigid tool's row also carries :func:`predicted_growth_per_s`: the growth rate of the
four-channel loop at rest, linearised along the contact normal, with the coupling damping the
engagement sets for the tool (:func:`coupling_damping_for_case`; positive: the tool bounces on the
floor whatever the haptic rate; with the configured damping it says which heavy rigid tools did).

``run_lighttools(out, quick=...)`` writes ``lighttools.json`` and returns the summary.
"""
from __future__ import annotations

import itertools
import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from ..protocol.codec import Hello
from ..protocol.messages import ServerState, ToolKind
from ..protocol.quaternion import quat_to_matrix_into
from ..protocol.session import ClientEndpoint
from ..protocol.transport import open_transport

KINDS = ("1dof", "planar", "spatial", "linkage-planar", "linkage-spatial")
MASSES_KG = (0.005, 0.01, 0.03, 0.1, 0.4, 2.0)
RATES_HZ = (500.0, 1000.0, 4000.0, 10000.0)
INERTIA_MIN_KG_M2 = 1e-7
ROD_LENGTH_M = 0.15          # the plausible moment of a rigid tool: a rod this long about its middle
BOX_HALF_M = 0.02            # the rigid tools' geometry: a 40 mm box
BAR_LENGTH_M = 0.06
BAR_WIDTH_M = 0.015
LINKS = 3
PUSH_N = 1.0
GAP_M = 0.001
EPSILON_M = 0.005
ENGINE_RATE_HZ = 60.0
SETTLE_S = 2.0
SETTLE_HEAVY_S = 5.0
WINDOW_S = 1.0
#: the floor's friction: a pure-force hand's push is tilted in the world by the device's index rotation
#: (the held link's tilt when the force ramped in), so on a frictionless floor a tool slides under it
#: (a 5 g planar chain at 2.4 mm/s, the device's damping balancing the push's 0.2 % sideways share)
MU_STATIC = 0.5
MU_KINETIC = 0.4
TWIST_MAX = 1e-3             # m/s and rad/s (the "twist below 1e-3 rad/s")
BALANCE_MAX = 0.02           # |F - push| / push
#: the quick grid (``--quick``, and the default suite's corners): lightest and heaviest, the smallest
#: moment and the plausible one, each kind, at 1 and 4 kHz
QUICK = (("1dof", 0.005, None, 1000.0), ("1dof", 2.0, None, 4000.0),
         ("planar", 0.005, 1e-7, 1000.0), ("planar", 2.0, None, 4000.0),
         ("spatial", 0.005, 1e-7, 4000.0), ("spatial", 0.1, 1e-7, 1000.0), ("spatial", 2.0, 1e-7, 1000.0),
         ("linkage-planar", 0.005, 1e-7, 1000.0), ("linkage-spatial", 0.005, 1e-7, 4000.0),
         ("linkage-spatial", 2.0, None, 1000.0))

_urls = itertools.count(1)
_NS = 1_000_000_000


@dataclass(frozen=True)
class Case:
    """One tool on one rate. ``inertia_kg_m2``: each principal moment of a rigid tool, each link's
    moment about z for a linkage (None for a 1dof tool)."""

    kind: str
    mass_kg: float
    inertia_kg_m2: float | None
    rate_hz: float

    @property
    def seconds(self) -> float:
        return (SETTLE_HEAVY_S if self.mass_kg >= 1.0 else SETTLE_S) + WINDOW_S

    @property
    def name(self) -> str:
        i = "-" if self.inertia_kg_m2 is None else f"{self.inertia_kg_m2:.3g}"
        return f"{self.kind} {self.mass_kg * 1e3:g} g I {i} {self.rate_hz:g} Hz"


def plausible_inertia_kg_m2(kind: str, mass_kg: float) -> float:
    """The largest moment the grid tries: a ``ROD_LENGTH_M`` rod of the tool's mass about its middle;
    for a linkage a ``BAR_LENGTH_M`` x ``BAR_WIDTH_M`` bar of one link's mass about its COM."""
    if kind.startswith("linkage"):
        m = mass_kg / LINKS
        return m * (BAR_LENGTH_M ** 2 + BAR_WIDTH_M ** 2) / 12.0
    return mass_kg * ROD_LENGTH_M ** 2 / 12.0


def inertias(kind: str, mass_kg: float) -> list[float | None]:
    """The decades from INERTIA_MIN_KG_M2 below the plausible moment, and the plausible moment."""
    if kind == "1dof":
        return [None]
    top = plausible_inertia_kg_m2(kind, mass_kg)
    out = []
    e = round(math.log10(INERTIA_MIN_KG_M2))
    while 10.0 ** e < top * (1 - 1e-9):
        out.append(float(f"1e{e}"))
        e += 1
    return out + [float(f"{top:.3g}")]


def grid(kinds=KINDS, masses=MASSES_KG, rates=RATES_HZ) -> list[Case]:
    return [Case(k, m, i, r) for r in rates for k in kinds for m in masses for i in inertias(k, m)]


def quick_grid() -> list[Case]:
    return [Case(k, m, i if i is not None or k == "1dof" else plausible_inertia_kg_m2(k, m), r)
            for k, m, i, r in QUICK]


# --------------------------------------------------------------------------- the engine
def _link_inertia6(izz: float) -> list[float]:
    # a bar's moments in proportion: I_xx (about its length) from its width, I_yy = I_zz
    ixx = izz * 2 * BAR_WIDTH_M ** 2 / (BAR_LENGTH_M ** 2 + BAR_WIDTH_M ** 2)
    return [ixx, izz, izz, 0.0, 0.0, 0.0]


def hello_for(case: Case) -> Hello:
    """The Hello the engine sends for ``case``'s tool."""
    common = dict(client_nonce=1, engine="lighttools-floor", max_contacts=32, epsilon_m=EPSILON_M,
                  env_rate_hz=ENGINE_RATE_HZ)
    if case.kind.startswith("linkage"):
        m = case.mass_kg / LINKS
        inertia = _link_inertia6(case.inertia_kg_m2)
        links = [dict(mass_kg=m, com_m=[BAR_LENGTH_M / 2, 0.0, 0.0], inertia_kg_m2=inertia, parent=-1, joint_type=0,
                      joint_axis=[0.0, 0.0, 1.0], joint_origin=[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])]
        for k in range(1, LINKS):
            links.append(dict(mass_kg=m, com_m=[BAR_LENGTH_M / 2, 0.0, 0.0], inertia_kg_m2=inertia, parent=k - 1,
                              joint_type=1, joint_axis=[0.0, 0.0, 1.0],
                              joint_origin=[BAR_LENGTH_M, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]))
        return Hello(tool_kind=ToolKind.LINKAGE, mass_kg=case.mass_kg, links=links, held_link=LINKS // 2, **common)
    tk = {"1dof": ToolKind.ONE_DOF, "planar": ToolKind.PLANAR, "spatial": ToolKind.SPATIAL}[case.kind]
    i = 0.0 if case.inertia_kg_m2 is None else case.inertia_kg_m2
    return Hello(tool_kind=tk, mass_kg=case.mass_kg, inertia_kg_m2=(i, i, i, 0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0),
                 **common)


class FloorEnv:
    """The engine of the module docstring: the floor y = 0, the tool following the newest
    ProxyState and stopped at the floor, its corners within EPSILON_M reported at ENGINE_RATE_HZ."""

    def __init__(self, url: str, clock, case: Case) -> None:
        self.case = case
        self.clock = clock
        self.tr = open_transport(url, "client")
        self.ep = ClientEndpoint(self.tr.send, hello_for(case))
        self.linkage = case.kind.startswith("linkage")
        self.planar = case.kind in ("planar", "linkage-planar")
        h = BOX_HALF_M
        if case.kind == "1dof":
            self.body = np.array([[0.0, -h, 0.0]])
        elif case.kind == "planar":
            self.body = np.array([[-h, -h, 0.0], [h, -h, 0.0]])
        elif case.kind == "spatial":
            self.body = np.array([[sx * h, -h, sz * h] for sx in (-1, 1) for sz in (-1, 1)])
        else:
            w = BAR_WIDTH_M / 2
            pts = [[0.0, -w, 0.0], [BAR_LENGTH_M, -w, 0.0], [BAR_LENGTH_M, w, 0.0], [0.0, w, 0.0]]
            if not self.planar:
                pts = [[x, y, s * w] for x, y, _ in pts for s in (-1, 1)]
            self.body = np.array(pts)
        # the tool's pose (x y z, w x y z) and joints: the proxy's start, GAP_M above the floor
        if self.linkage:
            self.pose = np.array([-BAR_LENGTH_M * LINKS / 2, BAR_WIDTH_M / 2 + GAP_M, 0.0, 1.0, 0.0, 0.0, 0.0])
        else:
            self.pose = np.array([0.0, BOX_HALF_M + GAP_M, 0.0, 1.0, 0.0, 0.0, 0.0])
        self.joints = np.zeros(LINKS - 1 if self.linkage else 0)
        self.started = False
        self.next_ns = 0
        self.states: list[tuple[int, int]] = []   # (ns, server_state) of every ProxyState
        self.rejected = ""
        self.updates_sent = 0

    def _frames(self):
        """(R, origin) of each body (the tool, or each bar) in the world."""
        q = self.pose[3:7] / np.linalg.norm(self.pose[3:7])
        R = quat_to_matrix_into(q, np.zeros((3, 3)))
        p = self.pose[:3].copy()
        out = [(R, p)]
        for j in self.joints:
            p = p + R @ np.array([BAR_LENGTH_M, 0.0, 0.0])
            c, s = math.cos(j), math.sin(j)
            R = R @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            out.append((R, p))
        return out

    def _points(self):
        return [(k, p + self.body @ R.T) for k, (R, p) in enumerate(self._frames())]

    def _stop_at_floor(self) -> None:
        low = min(float(pts[:, 1].min()) for _, pts in self._points())
        if low < 0.0:
            self.pose[1] -= low

    def contacts(self):
        keys, pos, nrm, sep = [], [], [], []
        for k, pts in self._points():
            for i, p in enumerate(pts):
                if p[1] <= EPSILON_M:
                    keys.append((k, 1, i))
                    pos.append((p[0], 0.0, p[2]))
                    nrm.append((0.0, 1.0, 0.0))
                    sep.append(p[1])
        n = len(keys)
        return (np.array(keys, dtype=np.int64).reshape(n, 3), np.array(pos, float).reshape(n, 3),
                np.array(nrm, float).reshape(n, 3), np.array(sep, float), np.zeros(n))

    def service(self) -> None:
        now = self.clock.now_ns()
        ep = self.ep
        if not self.started:
            ep.start(now)
            self.started = True
            self.next_ns = now
        while (got := self.tr.recv()) is not None:
            ps = ep.receive(got[0], got[1], now)
            if ps is not None:
                self.states.append((now, int(ps.server_state)))
                self.pose[:] = ps.proxy_pose
                if self.linkage:
                    self.joints = np.array(ps.joint_position, dtype=float)
                self._stop_at_floor()
        ep.poll(now)
        if ep.reject is not None and not self.rejected:
            self.rejected = f"Reject {ep.reject.code}: {ep.reject.reason}"
        if ep.established and now >= self.next_ns:
            k, p, n, d, v = self.contacts()
            extra = {"tool_joint_position": self.joints.copy()} if self.linkage else {}
            ep.send_contacts(now, now * 1e-9, self.pose.copy(), k, p, n, d, v, **extra)
            self.updates_sent += 1
            self.next_ns = now + int(round(_NS / ENGINE_RATE_HZ))

    def close(self) -> None:
        self.tr.close()


# --------------------------------------------------------------------------- one run
@dataclass
class Result:
    """What one run did (see the module docstring); ``refused``: the server's Reject, if any."""

    kind: str
    mass_kg: float
    inertia_kg_m2: float | None
    rate_hz: float
    seconds: float
    refused: str = ""
    linear_m_per_s: float = math.nan
    angular_rad_per_s: float = math.nan
    force_error_n: float = math.nan
    force_mean_n: float = math.nan
    not_engaged_states: int = 0
    proxy_states: int = 0
    state: str = ""
    fault: str = ""
    diverged: int = 0
    steps: int = 0

    @property
    def verdict(self) -> str:
        return verdict(self)


def verdict(r: Result) -> str:
    """``refused``, ``rests`` or what failed: ``fault <name>``, ``not engaged``, ``moving``,
    ``unbalanced``."""
    if r.refused:
        return "refused"
    if r.fault not in ("", "none") or r.diverged:
        return f"fault {r.fault}" if r.fault not in ("", "none") else "diverged"
    if r.not_engaged_states or r.proxy_states == 0:
        return "not engaged"
    if not (r.linear_m_per_s < TWIST_MAX and r.angular_rad_per_s < TWIST_MAX):
        return "moving"
    if not r.force_error_n <= BALANCE_MAX * PUSH_N:
        return "unbalanced"
    return "rests"


def settings_for(case: Case, url: str, **overrides):
    """The server's settings for ``case`` (its defaults but the rate, the device and the tool kind;
    ``overrides``: more sections merged in)."""
    from ..server import config as cfg

    dkind = {"linkage-planar": "planar", "linkage-spatial": "spatial"}.get(case.kind, case.kind)
    push = {"1dof": [-PUSH_N], "planar": [0.0, -PUSH_N, 0.0], "spatial": [0.0, -PUSH_N, 0.0, 0.0, 0.0, 0.0]}[dkind]
    device = {"driver": "sim", "kind": dkind, "hand": {"type": "constant", "wrench": push}}
    if dkind == "1dof":
        device["axis"] = [0.0, 1.0, 0.0]
    model = {"tool": "linkage" if case.kind.startswith("linkage") else "", "mu_static": MU_STATIC,
             "mu_kinetic": MU_KINETIC}
    if case.kind.startswith("linkage"):
        model["gravity_m_per_s2"] = (0.0, -min(9.81, 0.1 * PUSH_N / case.mass_kg), 0.0)
    base = {"loop": {"rate_hz": case.rate_hz}, "transport": {"url": url}, "device": device, "model": model,
            "telemetry": {"ring_s": 1.0}}
    for k, v in overrides.items():
        base.setdefault(k, {}).update(v)
    return cfg.load(base)


def run_case(case: Case, **overrides) -> Result:
    """Run ``case`` (module docstring) in simulated time; ``overrides``: config sections."""
    from ..server.clock import SimClock
    from ..server.lifecycle import Fault
    from ..server.loop import HapticLoop

    url = f"mem://lighttools-{os.getpid()}-{next(_urls)}"
    settings = settings_for(case, url, **overrides)
    clock = SimClock(start_ns=_NS)
    loop = HapticLoop.build(settings, clock=clock)
    env = None
    res = Result(case.kind, case.mass_kg, case.inertia_kg_m2, case.rate_hz, case.seconds)
    try:
        loop.warm_up()
        loop.start()
        env = FloorEnv(url, clock, case)
        n = int(round(case.seconds * case.rate_hz))
        w0 = n - int(round(WINDOW_S * case.rate_hz))
        w0_ns = None
        lin = ang = ferr = 0.0
        fsum = 0.0
        nf = 0
        rot = None
        for i in range(n):
            env.service()
            alive = loop.step()
            res.steps = i + 1
            if env.rejected:
                res.refused = env.rejected
                break
            if not alive:
                break
            if i >= w0:
                if w0_ns is None:
                    w0_ns = clock.now_ns()
                m = loop.model
                if m is None:
                    continue
                qd = np.abs(m.qd)
                if rot is None:
                    rot = _rotational(case.kind, len(qd))
                lin = max(lin, float(qd[~rot].max()))
                if rot.any():
                    ang = max(ang, float(qd[rot].max()))
                f = float(loop.ctrl.cmd[1])   # the world wrench the device renders: +y against the push
                ferr = max(ferr, abs(f - PUSH_N))
                fsum += f
                nf += 1
        if not res.refused:
            window = [s for t, s in env.states if w0_ns is not None and t >= w0_ns]
            res.proxy_states = len(window)
            res.not_engaged_states = sum(1 for s in window if s != int(ServerState.ENGAGED))
            res.linear_m_per_s, res.angular_rad_per_s = lin, ang
            res.force_error_n = ferr if nf else math.inf
            res.force_mean_n = fsum / nf if nf else math.nan
        res.state = loop.state_name
        res.fault = Fault(loop.fault).name.lower()
        res.diverged = int(loop.model.counters()["diverged"]) if loop.model is not None else 0
        return res
    finally:
        if env is not None:
            env.close()
        loop.close()


def _rotational(kind: str, dof: int) -> np.ndarray:
    """Which coordinates of the model's velocity are rotational (rad/s)."""
    rot = np.zeros(dof, dtype=bool)
    if kind == "1dof":
        return rot
    if kind in ("planar", "linkage-planar"):
        rot[2:] = True
    else:
        rot[3:] = True
    return rot


# --------------------------------------------------------------------------- why a heavy tool bounces
#: contacts the rigid tools rest on (their geometry above); a linkage's are not one spring
RIGID_CONTACTS = {"1dof": 1, "planar": 2, "spatial": 4}


def rest_growth_per_s(tool_mass_kg: float, device_mass_kg: float, device_damping_n_s_per_m: float,
                      contact_n_per_m: float, contact_n_s_per_m: float, coupling_n_per_m: float,
                      coupling_n_s_per_m: float, env_gain: float = 1.0) -> float:
    """The four-channel loop at rest on a contact, along its normal, in continuous time: the
    proxy (m_p) on the contact (k_e, b_e: every contact the tool rests on, summed) and the
    coupling (k_c, b_c) to the device's handle (m_d, its physical damping b_d); the device is
    rendered the environment's force (``env_gain`` x, the four-channel's force channel) less the
    coupling's, the proxy is given the hand's measured force (a constant push: it drops out of
    the linearisation)::

        m_p x_p'' = -k_e x_p - b_e x_p' + k_c (x_d - x_p) + b_c (x_d' - x_p')
        m_d x_d'' = -g (k_e x_p + b_e x_p') - k_c (x_d - x_p) - b_c (x_d' - x_p') - b_d x_d'

    Returns the largest real part of its eigenvalues [1/s]: above zero the resting tool's bounce
    grows at that rate whatever the haptic rate (the loop's own instability, not the step's).
    With ``env_gain`` 0 (the coupler) every mass is stable."""
    mp, md = float(tool_mass_kg), float(device_mass_kg)
    ke, be, kc, bc, bd, g = (float(contact_n_per_m), float(contact_n_s_per_m), float(coupling_n_per_m),
                             float(coupling_n_s_per_m), float(device_damping_n_s_per_m), float(env_gain))
    a = np.array([[0.0, 0.0, 1.0, 0.0],
                  [0.0, 0.0, 0.0, 1.0],
                  [(-ke - kc) / mp, kc / mp, (-be - bc) / mp, bc / mp],
                  [(kc - g * ke) / md, -kc / md, (bc - g * be) / md, (-bc - bd) / md]])
    return float(np.linalg.eigvals(a).real.max())


def predicted_growth_per_s(case: Case, **overrides) -> float | None:
    """:func:`rest_growth_per_s` for ``case``'s rigid tool on its contacts with the server's settings
    (``overrides`` as :func:`run_case` takes them) and its simulated device's mass and damping; None
    for a linkage or a controller without the force channel."""
    from ..server.devices.sim import effective_config

    if case.kind not in RIGID_CONTACTS:
        return None
    s = settings_for(case, "mem://lighttools-predict", **overrides)
    ctl, mdl = s["controller"], s["model"]
    if ctl["type"] != "four_channel":
        return None
    dev = effective_config({"kind": case.kind}, period_s=1.0 / case.rate_hz)
    n = RIGID_CONTACTS[case.kind]
    return rest_growth_per_s(case.mass_kg, dev["mass_kg"], dev["damping_n_s_per_m"], n * mdl["stiffness_n_per_m"],
                             n * mdl["damping_n_s_per_m"], ctl["stiffness_n_per_m"], coupling_damping_for_case(case, s),
                             ctl["env_gain"])


def coupling_damping_for_case(case: Case, settings) -> float:
    """The coupling damping the server sets for ``case``'s rigid tool (``control.Controller.fit_tool``:
    ``stability.coupling_damping_for_tool`` with the simulated device's mass, the config's stated
    device damping and the model's capacity)."""
    from ..server.devices.sim import effective_config
    from ..server.stability import coupling_damping_for_tool

    ctl, mdl, pas = settings["controller"], settings["model"], settings["passivity"]
    dev = effective_config({"kind": case.kind}, period_s=1.0 / case.rate_hz)
    b = coupling_damping_for_tool(
        case.mass_kg, device_mass_kg=pas["moving_mass_kg"] or dev["mass_kg"],
        device_damping_n_s_per_m=pas["device_damping_n_s_per_m"], contact_n_per_m=mdl["stiffness_n_per_m"],
        contact_n_s_per_m=mdl["damping_n_s_per_m"], max_contacts=mdl["capacity"],
        coupling_n_per_m=ctl["stiffness_n_per_m"], coupling_n_s_per_m=ctl["damping_n_s_per_m"], env_gain=ctl["env_gain"])
    return ctl["damping_n_s_per_m"] if b is None else b


# --------------------------------------------------------------------------- the sweep
def run_lighttools(out: str | None, *, quick: bool = False, cases=None, log=None) -> dict:
    """Run the grid (``quick``: :func:`quick_grid`), write ``lighttools.json`` into ``out`` (if
    given) and return ``{"rows": [...], "counts": {verdict: n}, "summary": [lines]}``."""
    cases = list(cases) if cases is not None else (quick_grid() if quick else grid())
    rows = []
    for i, c in enumerate(cases):
        r = run_case(c)
        row = asdict(r)
        row["verdict"] = r.verdict
        row["predicted_growth_per_s"] = predicted_growth_per_s(c)
        rows.append(row)
        if log is not None:
            log(f"lighttools {i + 1}/{len(cases)} {c.name}: {_line(row)}")
    counts: dict[str, int] = {}
    for row in rows:
        counts[row["verdict"]] = counts.get(row["verdict"], 0) + 1
    res = {"rows": rows, "counts": counts, "twist_max": TWIST_MAX, "balance_max_n": BALANCE_MAX * PUSH_N,
           "push_n": PUSH_N, "window_s": WINDOW_S}
    res["summary"] = summary_lines(res)
    if out:
        os.makedirs(out, exist_ok=True)
        with open(os.path.join(out, "lighttools.json"), "w", encoding="utf-8") as fh:
            json.dump(res, fh, indent=1)
    return res


def _line(row: dict) -> str:
    if row["refused"]:
        return f"refused ({row['refused']})"
    g = row.get("predicted_growth_per_s")
    why = "" if g is None or row["verdict"] == "rests" else f" (the four-channel loop's growth {g:+.2g}/s)"
    return (f"{row['verdict']}: v {row['linear_m_per_s']:.2g} m/s, w {row['angular_rad_per_s']:.2g} rad/s, "
            f"|F - push| {row['force_error_n']:.2g} N{why}")


def summary_lines(res: dict) -> list[str]:
    """One line per (kind, rate): runs, how many rest, the worst speeds and force error among them,
    and every run that did not rest."""
    lines = []
    by: dict[tuple[str, float], list[dict]] = {}
    for row in res["rows"]:
        by.setdefault((row["kind"], row["rate_hz"]), []).append(row)
    for (kind, rate), rows in by.items():
        ok = [r for r in rows if r["verdict"] == "rests"]
        worst = (f"; worst v {max(r['linear_m_per_s'] for r in ok):.2g} m/s, w "
                 f"{max(r['angular_rad_per_s'] for r in ok):.2g} rad/s, |F - push| "
                 f"{max(r['force_error_n'] for r in ok):.2g} N") if ok else ""
        lines.append(f"lighttools {kind} {rate:g} Hz: {len(ok)}/{len(rows)} rest{worst}")
        for r in rows:
            if r["verdict"] != "rests":
                i = "-" if r["inertia_kg_m2"] is None else f"{r['inertia_kg_m2']:.3g}"
                lines.append(f"  {r['mass_kg'] * 1e3:g} g, I {i}: {_line(r)}")
    return lines


def summary_json(res: dict) -> str:
    return json.dumps(res, indent=1)
