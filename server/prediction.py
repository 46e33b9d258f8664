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

Everything runs once per model update (30-60 Hz), in plain Python floats; nothing per haptic
step. The loop calls :meth:`EngineAdvice.on_update` after applying a ContactUpdate and puts
:attr:`epsilon_m` and :attr:`lead_s` into the ProxyState it acknowledges with.
"""
from __future__ import annotations

import math

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


def _floats(v, n: int) -> list[float]:
    """The first ``n`` values of a numpy array or a sequence, as Python floats."""
    tolist = getattr(v, "tolist", None)
    out = tolist() if tolist is not None else [float(x) for x in v]
    return out[:n] if len(out) != n else out


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
        self.cap = float(epsilon_cap_m)
        self.radius = float(tool_radius_m)
        self.predict = bool(predict)
        self.use_lead = bool(lead)
        self.floor = min(float(epsilon_floor_m), self.cap)
        self.margin = float(margin)
        self.lead_max = float(lead_max_s)
        self._t = math.nan          # server time of the last update, s
        self._period = 0.0          # decaying max of the update interval, s
        self._speed = 0.0           # decaying max of the fastest point's speed, m/s
        self._v_last = 0.0
        self._lag = 0.0             # the latest residual lag measured in free motion, s
        self._dist = 0.0            # the engine tool's distance from the proxy at the last update, m
        self._lead = 0.0
        self.epsilon_m = self.cap   # until something has been measured: the granted epsilon
        self.lead_s = 0.0
        self.lag_samples = 0

    def on_update(self, now_s: float, proxy_pose, proxy_twist, engine_tool_pose, tool_touching: bool) -> None:
        """After the loop applied a ContactUpdate: ``now_s`` the server clock, ``proxy_pose`` /
        ``proxy_twist`` the proxy's tool frame (as in ProxyState: x y z qw qx qy qz; v (3), w (3),
        world), ``engine_tool_pose`` the update's ``tool_pose``, ``tool_touching``: some contact of
        the update has separation <= 0 (the engine's tool touches something)."""
        now = float(now_s)
        # one conversion per vector (numpy arrays in the loop, sequences elsewhere): reading a
        # numpy element at a time costs more than the arithmetic below
        vx, vy, vz, wx, wy, wz = _floats(proxy_twist, 6)
        px, py, pz, pqw, pqx, pqy, pqz = _floats(proxy_pose, 7)
        ex, ey, ez, eqw, eqx, eqy, eqz = _floats(engine_tool_pose, 7)
        v_lin = math.sqrt(vx * vx + vy * vy + vz * vz)
        speed = v_lin + math.sqrt(wx * wx + wy * wy + wz * wz) * self.radius
        if not math.isfinite(speed):
            return
        dt = now - self._t if math.isfinite(self._t) else 0.0
        self._t = now
        decay = math.exp(-dt / MEMORY_S) if dt > 0 else 1.0
        if dt > 0:
            self._period = max(dt, self._period * decay)
        accel = max(0.0, (speed - self._v_last) / dt) if dt > 0 else 0.0
        self._v_last = speed
        self._speed = max(speed, self._speed * decay)
        # how far the engine's tool (where the contacts are computed) is from the proxy
        dx = px - ex
        dy = py - ey
        dz = pz - ez
        dot = abs(((pqw * eqw + pqx * eqx) + pqy * eqy) + pqz * eqz)
        angle = 2.0 * math.acos(min(1.0, dot))
        dist = math.sqrt(dx * dx + dy * dy + dz * dz) + angle * self.radius
        if not math.isfinite(dist):
            return
        self._dist = dist
        # the engine tool's lag behind the proxy, along the motion, where nothing holds it back
        if v_lin > LAG_MIN_SPEED_M_PER_S and not tool_touching:
            lag = (dx * vx + dy * vy + dz * vz) / (v_lin * v_lin)
            if math.isfinite(lag):
                self._lag = min(max(lag, -LAG_MAX_S), LAG_MAX_S)
                self.lag_samples += 1
                if self.use_lead:
                    self._lead = min(max(self._lead + LEAD_GAIN * self._lag, 0.0), self.lead_max)
        self.lead_s = self._lead if self.use_lead else 0.0
        if self.predict and self.cap > 0:
            v = max(self._speed, speed + accel * self._period)
            self.epsilon_m = min(self.cap, max(self.floor, self.margin * v * self._period + dist))
        else:
            self.epsilon_m = self.cap

    @property
    def lag_s(self) -> float:
        """The last residual lag of the engine's tool behind the proxy measured in free motion, s."""
        return self._lag

    @property
    def distance_m(self) -> float:
        """How far the engine's tool was from the proxy at the last update (the reach of the
        tool's points included), m."""
        return self._dist

    @property
    def period_s(self) -> float:
        """The engine's longest recent update interval (decaying maximum), s."""
        return self._period
