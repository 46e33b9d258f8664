"""What the server tells the engine so the surface is felt where it is (issue 15, items 2 and 3).

A contact reaches the local model one engine period (plus the engine's lag) after the engine's
tool met it; by then the proxy went on, and the update rules keep that overshoot as a
deformation (eqs. 4/5). Two things the server can measure close the gap:

- **the epsilon to use next** (``epsilon_m``): the engine reports contacts within epsilon of its
  tool; a wall the proxy reaches before the next update is applied must be within epsilon of the
  engine's tool now. The proxy is ``D`` away from the engine's tool (its tool frame's distance
  plus the angle between them times ``tool_radius_m``, the reach of the tool's points) and moves
  at most ``v T`` before the next update, with ``v`` its fastest point's speed (raised by its
  recent acceleration) and ``T`` the engine's longest recent step, so
  ``epsilon = margin v T + D``, never below ``epsilon_floor_m`` and never above the epsilon
  granted in the handshake (the cap): fast approaches are predicted, slow ones not inflated;
- **the lead** (``lead_s``): the time the engine should extrapolate the proxy's pose by
  (``proxy_pose`` advanced along ``proxy_twist`` by ``lead_s`` plus the time since the
  ProxyState arrived) so its tool stays on the proxy instead of behind it. The server measures
  the engine tool's lag behind the proxy in free motion (where nothing holds the tool back):
  ``L = (p_proxy - p_tool) . v / |v|^2`` at the arrival of each update, i.e. the update's
  network delay, the engine's step and its tracking lag; an engine that follows the lead makes
  ``L`` its residual, so the lead integrates it (``lead += gain L``, bounded by ``lead_max_s``).

Everything runs once per model update (30-60 Hz), nothing per haptic step, in one numba kernel
(``advice_update``) over a state array: the step that acknowledges an update pays about 1 us
for it (in Python floats it was 12 us). The loop calls :meth:`EngineAdvice.on_update` in the
step after the one that applied a ContactUpdate and puts :attr:`epsilon_m` and :attr:`lead_s`
into the ProxyState it acknowledges with.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .readonly import ArrayBool, ArrayFloat, ArrayInt

#: Prediction margin over the distance the fastest point travels before the next update.
EPSILON_MARGIN = 1.5
#: The smallest epsilon told to an engine, m (a resting or slow tool: contacts at zero clearance,
#: e.g. an exactly fitting hole's walls, stay in the model).
EPSILON_FLOOR_M = 0.002
#: The engine period and the speed are remembered as decaying maxima (time constant, s): a
#: variable-rate engine's longest step, and a fast approach that slows down, are not forgotten
#: at once.
MEMORY_S = 0.5
#: Lag measurements need the proxy to move faster than this (m/s) and the engine's tool to be
#: free (no contact of it touching: a wall holding the tool back is not lag).
LAG_MIN_SPEED_M_PER_S = 0.02
#: Gain of the lead's integration of the measured residual lag, and its bounds (s).
LEAD_GAIN = 0.5
LEAD_MAX_S = 0.1
#: The measured lag is clipped to this (s) before use (a single odd sample cannot blow it up).
LAG_MAX_S = 0.2


def tool_radius_m(mass_kg: float, inertia_diag_kg_m2) -> float:
    """A tool's reach from its centre of mass estimated from its inertia: sqrt(3 I_max / m) is
    half the length of a rod and the half-diagonal of a rectangle (exact for both), 1.1 R for a
    ball. 0 for a tool without inertia (a 1-DOF tool translates only)."""
    m = float(mass_kg)
    i_max = max((float(v) for v in inertia_diag_kg_m2), default=0.0)
    if not (m > 0 and i_max > 0 and math.isfinite(i_max)):
        return 0.0
    return math.sqrt(3.0 * i_max / m)


# the advice's state (A_*) and parameters (P_*), one float64 array each: the kernel reads and
# writes them in place, the class reads them out
A_T, A_PERIOD, A_SPEED, A_V_LAST, A_LAG, A_DIST, A_LEAD, A_EPSILON, A_LEAD_OUT, A_LAG_SAMPLES = range(10)
P_CAP, P_RADIUS, P_PREDICT, P_USE_LEAD, P_FLOOR, P_MARGIN, P_LEAD_MAX = range(7)


@njit(cache=True)
def advice_update(a, p, now, pp, tw, ep, separation_m, touching):
    """One update's advice (see the module docstring and :meth:`EngineAdvice.on_update`): ``pp``
    / ``tw`` the proxy's pose and twist, ``ep`` the engine's tool pose; the engine's tool touches
    something if ``touching`` or any ``separation_m`` <= 0."""
    for j in range(separation_m.shape[0]):
        if separation_m[j] <= 0.0:
            touching = True
    vx, vy, vz, wx, wy, wz = tw[0], tw[1], tw[2], tw[3], tw[4], tw[5]
    v_lin = math.sqrt(vx * vx + vy * vy + vz * vz)
    speed = v_lin + math.sqrt(wx * wx + wy * wy + wz * wz) * p[P_RADIUS]
    if not math.isfinite(speed):
        return
    t_last = a[A_T]
    dt = now - t_last if math.isfinite(t_last) else 0.0
    a[A_T] = now
    decay = math.exp(-dt / MEMORY_S) if dt > 0 else 1.0
    if dt > 0:
        a[A_PERIOD] = max(dt, a[A_PERIOD] * decay)
    accel = max(0.0, (speed - a[A_V_LAST]) / dt) if dt > 0 else 0.0
    a[A_V_LAST] = speed
    a[A_SPEED] = max(speed, a[A_SPEED] * decay)
    # how far the engine's tool (where the contacts are computed) is from the proxy
    dx = pp[0] - ep[0]
    dy = pp[1] - ep[1]
    dz = pp[2] - ep[2]
    dot = abs(((pp[3] * ep[3] + pp[4] * ep[4]) + pp[5] * ep[5]) + pp[6] * ep[6])
    angle = 2.0 * math.acos(min(1.0, dot))
    dist = math.sqrt(dx * dx + dy * dy + dz * dz) + angle * p[P_RADIUS]
    if not math.isfinite(dist):
        return
    a[A_DIST] = dist
    use_lead = p[P_USE_LEAD] != 0.0
    # the engine tool's lag behind the proxy, along the motion, where nothing holds it back
    if v_lin > LAG_MIN_SPEED_M_PER_S and not touching:
        lag = (dx * vx + dy * vy + dz * vz) / (v_lin * v_lin)
        if math.isfinite(lag):
            a[A_LAG] = min(max(lag, -LAG_MAX_S), LAG_MAX_S)
            a[A_LAG_SAMPLES] += 1.0
            if use_lead:
                a[A_LEAD] = min(max(a[A_LEAD] + LEAD_GAIN * a[A_LAG], 0.0), p[P_LEAD_MAX])
    a[A_LEAD_OUT] = a[A_LEAD] if use_lead else 0.0
    cap = p[P_CAP]
    if p[P_PREDICT] != 0.0 and cap > 0:
        period = a[A_PERIOD]
        v = max(a[A_SPEED], speed + accel * period)
        a[A_EPSILON] = min(cap, max(p[P_FLOOR], p[P_MARGIN] * v * period + dist))
    else:
        a[A_EPSILON] = cap


_NO_SEPARATION = np.zeros(0)
_NO_SEPARATION.flags.writeable = False  # the type of the decoder's read-only column views


def _f8(v, n: int) -> np.ndarray:
    if type(v) is np.ndarray and v.dtype == np.float64 and v.ndim == 1 and v.flags.c_contiguous:
        return v
    a = np.ascontiguousarray(v, dtype=np.float64).reshape(-1)
    if a.shape[0] < n:
        raise ValueError(f"expected {n} numbers, got {a.shape[0]}")
    return a


class EngineAdvice:
    """The epsilon and the lead to tell the engine (see the module docstring).

    ``epsilon_cap_m``: the epsilon granted in the handshake (``Welcome.epsilon_m``; 0 turns the
    prediction off: an LM0 server); ``tool_radius_m``: the reach of the tool's points from the
    tool frame's origin (``tool_radius_m()`` plus the COM offset); ``predict`` / ``lead``: each
    half can be switched off (then ``epsilon_m`` is the cap and ``lead_s`` 0, the paper's
    behaviour)."""

    def __init__(self, epsilon_cap_m: float, *, tool_radius_m: float = 0.0, predict: bool = True, lead: bool = True,
                 epsilon_floor_m: float = EPSILON_FLOOR_M, margin: float = EPSILON_MARGIN,
                 lead_max_s: float = LEAD_MAX_S) -> None:
        for name, v in (("epsilon_cap_m", epsilon_cap_m), ("tool_radius_m", tool_radius_m),
                        ("epsilon_floor_m", epsilon_floor_m), ("lead_max_s", lead_max_s)):
            if not (math.isfinite(float(v)) and float(v) >= 0):
                raise ValueError(f"{name}: must be a finite number >= 0, got {v!r}")
        if not (math.isfinite(float(margin)) and float(margin) >= 1.0):
            raise ValueError(f"margin: must be >= 1, got {margin!r}")
        cap = float(epsilon_cap_m)
        self._p = np.array([cap, float(tool_radius_m), float(bool(predict)), float(bool(lead)),
                            min(float(epsilon_floor_m), cap), float(margin), float(lead_max_s)])
        self._a = np.zeros(10)
        #: ``(a, p)`` for :func:`advice_update` called from another kernel (the loop's
        #: acknowledgement: the proxy's state and the advice in one call)
        self.kernel_arrays = (self._a, self._p)
        self._a[A_T] = math.nan  # server time of the last update, s
        self._a[A_EPSILON] = cap  # until something has been measured: the granted epsilon

    cap = ArrayFloat("_p", P_CAP, doc="The epsilon granted in the handshake, m.")
    radius = ArrayFloat("_p", P_RADIUS, doc="The reach of the tool's points from the tool frame, m.")
    floor = ArrayFloat("_p", P_FLOOR, doc="The smallest epsilon told, m.")
    margin = ArrayFloat("_p", P_MARGIN, doc="The prediction margin.")
    lead_max = ArrayFloat("_p", P_LEAD_MAX, doc="The lead's bound, s.")
    predict = ArrayBool("_p", P_PREDICT, doc="The epsilon is predicted (else: the cap).")
    use_lead = ArrayBool("_p", P_USE_LEAD, doc="The lead is integrated (else: 0).")
    epsilon_m = ArrayFloat("_a", A_EPSILON, doc="The epsilon to tell the engine next, m.")
    lead_s = ArrayFloat("_a", A_LEAD_OUT, doc="The lead to tell the engine next, s.")
    lag_samples = ArrayInt("_a", A_LAG_SAMPLES, doc="Lag measurements taken (free motion only).")

    def on_update(self, now_s: float, proxy_pose, proxy_twist, engine_tool_pose, tool_touching: bool = False,
                  separation_m=_NO_SEPARATION) -> None:
        """After the loop applied a ContactUpdate: ``now_s`` the server clock, ``proxy_pose`` /
        ``proxy_twist`` the proxy's tool frame (as in ProxyState: x y z qw qx qy qz; v (3), w (3),
        world), ``engine_tool_pose`` the update's ``tool_pose``, ``tool_touching``: the engine's
        tool touches something, as does any of the update's ``separation_m`` <= 0 (the loop
        passes the update's column and lets the kernel look)."""
        advice_update(self._a, self._p, float(now_s), _f8(proxy_pose, 7), _f8(proxy_twist, 6),
                      _f8(engine_tool_pose, 7), separation_m, bool(tool_touching))

    @property
    def lag_s(self) -> float:
        """The last residual lag of the engine's tool behind the proxy measured in free motion, s."""
        return float(self._a[A_LAG])

    @property
    def distance_m(self) -> float:
        """How far the engine's tool was from the proxy at the last update (the reach of the
        tool's points included), m."""
        return float(self._a[A_DIST])

    @property
    def period_s(self) -> float:
        """The engine's longest recent update interval (decaying maximum), s."""
        return float(self._a[A_PERIOD])


def warm_up() -> None:
    """Compile / load the kernel with the types the loop passes (its own float64 arrays, the
    update's read-only pose and separation views)."""
    ro = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    ro.flags.writeable = False
    sep = np.ones(2)
    sep.flags.writeable = False
    adv = EngineAdvice(0.01)
    adv.on_update(0.0, ro.copy(), np.zeros(6), ro, False, sep)
    adv.on_update(0.01, ro.copy(), np.zeros(6), ro, False, _NO_SEPARATION)
