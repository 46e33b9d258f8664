"""The passivity layer: an energy tank under the controller, as two small pure kernels.

The two-layer idea (Franken, Stramigioli et al., IEEE T-RO 2011): the controller above stays
what it is (transparency); below it, before the safety filter, a tank of energy decides how much
of the command may *give* energy to the hand. The tank is the running balance of the hand's
port (``control.port_energy``: each command held over a period times the handle's displacement
during it), so the server can never give the hand more than the tank held at the start, (a
share of) what the hand put in, what the device's own damping dissipated and what an engine
granted, but for the error of one period's prediction (L5). Energy the hand puts in and the
controller's dampers then dissipate stays counted in the tank (it entered
the port and did not come back out): counting the coupling damper's dissipation on top would
count it twice. The device's physical damping is outside the port (the motor's work minus it is
what reaches the hand), so it feeds the tank: ``b |dx|^2 / T`` per period, the least a viscous
damper ``b`` dissipates over a displacement ``dx`` in ``T`` (Cauchy-Schwarz), with ``b`` as the
config declares it, else as the device states it, else 0 (``damping_figures``).

Layouts (declared once; the controller embeds them as blocks of its arrays, ``CP_TANK``,
``CS_TANK``, ``CC_TANK``):

- ``tp`` parameters, float64[NTP]: ``TP_*`` below.
- ``ts`` state, float64[NTS]: the tank level and its books.
- ``tc`` counters, int64[NTC].

Contract of ``account(tp, ts, w_j, dx2_m2, dr2_rad2)`` (after the ledger paired the last period;
``w_j`` is the energy given to the hand over it, ``dx2_m2`` / ``dr2_rad2`` the squared
displacement and rotation of the handle during it):

A1. A non-finite ``w_j`` (or squared motion) changes nothing but the count ``TS_BAD``.
A2. Otherwise ``H1 = min(TP_HMAX, H0 - max(w_j, 0) + k max(-w_j, 0) + (TP_BDEV dx2 + TP_BRDEV
    dr2) / TP_PERIOD)`` with ``k = TP_CREDIT`` in (0, 1]: the hand's energy drains it, the share
    ``k`` of what the hand puts in and the declared damping feed it, the cap bounds what a hand
    can store for later. With ``k = 1`` the tank is lossless: a handle bouncing on an undamped
    wall under a constant push is passive and keeps bouncing on the energy it brought; with
    ``k < 1`` the layer dissipates the rest, so an exchange that gives back what it took (a
    bounce, a limit cycle) drains the tank and, once the allowance (L2) runs short, dies out.
    ``TS_GIVEN`` / ``TS_TAKEN`` / ``TS_DAMPED`` add the positive part, the negative part of
    ``w_j`` (all of it) and the damping's share.

``grant(tp, ts, e_j)``: an engine's declared work on the tool (``ContactUpdate.work_on_tool_j``)
is added like the hand's input (capped at ``TP_HMAX``); a negative or non-finite grant adds
nothing (the caller refuses it by name before).

Contract of ``limit(tp, ts, tc, cmd, twist, hand, prev, force_rate, torque_rate)`` (``cmd`` the
controller's wrench, device frame, in place; ``twist`` the handle's twist and ``hand`` the hand's
measured wrench on the handle, device frame, a non-finite hand component read as 0: no sensor;
``prev`` the wrench the device renders now, the safety filter's last output, and ``force_rate`` /
``torque_rate`` the filter's largest change per period). The layer predicts the work a held
command does over the next period from the handle's dynamics and keeps it within what the tank
can pay once the force already rendered has been withdrawn.

Write ``g`` for a force held over the period, ``v`` the sampled velocity, ``h`` the hand's force,
``T = TP_PERIOD``, ``m = TP_MASS`` (the moving mass at the handle as the device states it) and
``a = T^2 / m``; torques alike with ``TP_INERTIA`` (the smallest principal moment). Over a period
of a zero-order hold the handle moves ``dx = v T + (g + h) T^2 / (2 m)`` (``v T + (g + h) T^2 / m``
under a semi-implicit Euler step, as the simulated device integrates: the prediction takes the
larger), so the command's work is predicted as

    P(g) = T g . v + a g . (g + h)

The quadratic term is the motion the force itself causes within the period, positive whatever
its direction: why a force across the motion turns the velocity towards itself and then gives
energy, and why an energy-taking damper ``-c v`` gives energy once ``c > m / T``. The rendered
force ``p`` cannot vanish at once: the safety filter withdraws it over ``tau = |p| T / rate``, and
with the force ramped down linearly over ``tau`` from the current velocity it does

    R(p) = max(0, tau p . v / 2 + tau^2 (|p|^2 / 8 + p . h / 6) / m)

(``reserve``; torque alike). ``H`` the tank level, ``H' = H - R(p_force) - R(p_torque)`` what is
left once that is paid, ``L = TP_HLOW``:

L1. Off (``TP_ON == 0``): the command is unchanged. On, with ``H' >= L`` and ``P <= H' / 2`` for
    the force and for the torque: unchanged.
L2. The period's allowance is a C1 function of ``H'``: ``A = (1 - beta(H')) max(H', 0)``, with
    ``beta`` 1 at ``H' <= 0``, 0 at ``H' >= L``, ``s^2 (3 - 2 s)`` with ``s = 1 - H' / L`` between
    (``beta_of``; ``TS_BETA``). So ``A = 0`` at an empty tank, ``~ 3 H'^3 / L^2`` near it, ``H'``
    from ``L`` up, ``dA/dH'`` continuous and at most 27/16 (no step in the level's effect: the
    chatter a switched passivity controller has). The force and the torque get half each.
L3. The force is the nearest point to the controller's of ``{g : P(g) <= A / 2}``, a ball
    (centre ``c = -(m v / T + h) / 2``, radius ``sqrt(A / (2 a) + |c|^2)``) that always holds 0
    and, at rest, the force that balances the hand (a hand held by a wall keeps its wall at an
    empty tank); the torque alike. ``|f' - f|`` is the distance to the ball.
L4. Continuous in the command (1-Lipschitz: the projection on a convex set), the velocity, the
    hand, the rendered wrench and the level. The safety filter after the layer bounds every
    output step by its rate limit; its caps scale a force towards 0, which stays in the ball.
L5. With ``H' <= 0`` the output is predicted to give nothing (``P(f') <= 0``, ``P(t') <= 0``).
    What still reaches the hand is the prediction's error (the hand's force changing within a
    period, the velocity changing while a force is withdrawn, the rate limit's lag behind a ball
    that moves faster than it, a device lighter than stated),
    paid from the margin ``L``: limiting starts before the tank is empty.
L6. Finite in, finite out (a non-finite command, twist or rendered wrench passes unchanged: the
    safety filter faults on a non-finite command); ``tc[TC_LIMITED]`` counts calls that changed
    the command, ``tc[TC_EMPTY]`` calls with ``H <= 0``.

``reset(tp, ts)``: the tank at ``TP_H0`` and its books at zero.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy")

# ---- parameters (float64[NTP])
TP_ON = 0          # 1: limit the command when the tank is short; 0: account only
TP_H0 = 1          # the initial budget, J
TP_HMAX = 2        # the tank's cap, J
TP_HLOW = 3        # below this level (less the reserve) the allowance shrinks (L2), J
TP_MASS = 4        # the moving mass at the handle, kg (the work prediction's ZOH term)
TP_INERTIA = 5     # the smallest principal moment of inertia at the handle, kg m^2
TP_BDEV = 6        # the device's declared viscous damping, N s/m
TP_BRDEV = 7       # and rotational, N m s/rad
TP_PERIOD = 8      # the haptic period, s
TP_GRANTS = 9      # 1: engines' grants feed the tank
TP_CREDIT = 10     # the share of the energy the hand puts in that feeds the tank, (0, 1]
NTP = 11

# ---- state (float64[NTS])
TS_TANK = 0        # the tank level, J
TS_GIVEN = 1       # energy given to the hand over the paired periods, J (>= 0)
TS_TAKEN = 2       # energy the hand put in, J (>= 0)
TS_DAMPED = 3      # energy the declared device damping dissipated, J
TS_GRANTED = 4     # energy engines granted, J
TS_BETA = 5        # the last limiting factor, 0..1
TS_LOW = 6         # the lowest level the tank reached, J
TS_BAD = 7         # periods not accounted (non-finite input)
NTS = 8

# ---- counters (int64[NTC])
TC_LIMITED = 0     # calls in which the layer changed the command
TC_EMPTY = 1       # calls with the tank at or below zero
NTC = 2


@njit(**_JIT)
def reset(tp, ts):
    """The tank at its initial budget, its books at zero."""
    for j in range(NTS):
        ts[j] = 0.0
    ts[TS_TANK] = tp[TP_H0]
    ts[TS_LOW] = tp[TP_H0]


@njit(**_JIT)
def account(tp, ts, w_j, dx2_m2, dr2_rad2):
    """One paired period into the tank (contract A1-A2)."""
    if not (math.isfinite(w_j) and math.isfinite(dx2_m2) and math.isfinite(dr2_rad2)):
        ts[TS_BAD] += 1.0
        return
    damped = 0.0
    if tp[TP_PERIOD] > 0.0:
        damped = (tp[TP_BDEV] * dx2_m2 + tp[TP_BRDEV] * dr2_rad2) / tp[TP_PERIOD]
    if w_j > 0.0:
        ts[TS_GIVEN] += w_j
    else:
        ts[TS_TAKEN] -= w_j
    ts[TS_DAMPED] += damped
    h = min(tp[TP_HMAX], ts[TS_TANK] - (w_j if w_j > 0.0 else tp[TP_CREDIT] * w_j) + damped)
    ts[TS_TANK] = h
    if h < ts[TS_LOW]:
        ts[TS_LOW] = h


@njit(**_JIT)
def grant(tp, ts, e_j):
    """An engine's declared work on the tool, into the tank (capped). Returns the energy added."""
    if tp[TP_GRANTS] == 0.0 or not math.isfinite(e_j) or e_j <= 0.0:
        return 0.0
    h0 = ts[TS_TANK]
    h = min(tp[TP_HMAX], h0 + e_j)  # h0 <= TP_HMAX always (``account`` and ``reset`` keep it)
    ts[TS_TANK] = h
    ts[TS_GRANTED] += h - h0
    return h - h0


@njit(**_JIT)
def beta_of(tp, h):
    """The limiting factor of a tank level (contract L2)."""
    low = tp[TP_HLOW]
    if h >= low:
        return 0.0
    if h <= 0.0:
        return 1.0
    s = 1.0 - h / low
    return s * s * (3.0 - 2.0 * s)


@njit(**_JIT)
def allowance(tp, h):
    """The period's allowance ``A(H) = (1 - beta(H)) max(H, 0)`` (contract L2), J."""
    if h <= 0.0:
        return 0.0
    return (1.0 - beta_of(tp, h)) * h


@njit(**_JIT)
def _limit3(cmd, o, twist, hand, allow, period, mass):
    """cmd[o:o+3] to the nearest point of ``{g : P(g) <= allow}`` (contract L3). True when it
    changed."""
    a = period * period / mass
    # P(g) = a |g - c|^2 - a |c|^2 with c = -(T v + a h) / (2 a)
    hj = hand[o] if math.isfinite(hand[o]) else 0.0
    c0 = -0.5 * (period * twist[o] / a + hj)
    hj = hand[o + 1] if math.isfinite(hand[o + 1]) else 0.0
    c1 = -0.5 * (period * twist[o + 1] / a + hj)
    hj = hand[o + 2] if math.isfinite(hand[o + 2]) else 0.0
    c2 = -0.5 * (period * twist[o + 2] / a + hj)
    r2 = allow / a + c0 * c0 + c1 * c1 + c2 * c2
    d0 = cmd[o] - c0; d1 = cmd[o + 1] - c1; d2 = cmd[o + 2] - c2
    n2 = d0 * d0 + d1 * d1 + d2 * d2
    if n2 <= r2:
        return False
    k = math.sqrt(max(r2, 0.0) / n2)
    cmd[o] = c0 + k * d0
    cmd[o + 1] = c1 + k * d1
    cmd[o + 2] = c2 + k * d2
    return True


@njit(**_JIT)
def reserve(prev, o, twist, hand, rate, period, mass):
    """The work the rendered force ``p = prev[o:o+3]`` does while the safety filter's rate limit
    withdraws it (contract L3): ``max(0, tau p . v / 2 + tau^2 (|p|^2 / 8 + p . h / 6) / m)``,
    ``tau = |p| T / rate``, J."""
    n2 = prev[o] * prev[o] + prev[o + 1] * prev[o + 1] + prev[o + 2] * prev[o + 2]
    if not (n2 > 0.0 and rate > 0.0):
        return 0.0
    tau = math.sqrt(n2) * period / rate
    pv = 0.0
    ph = 0.0
    for j in range(o, o + 3):
        pv += prev[j] * twist[j]
        if math.isfinite(hand[j]):
            ph += prev[j] * hand[j]
    r = 0.5 * tau * pv + tau * tau * (0.125 * n2 + ph / 6.0) / mass
    return r if r > 0.0 else 0.0


@njit(**_JIT)
def limit(tp, ts, tc, cmd, twist, hand, prev, force_rate, torque_rate):
    """The command kept within the work the tank can pay for the next period, less what
    withdrawing the rendered wrench ``prev`` at the safety filter's rates (per period) will give
    (contract L1-L6), in place."""
    h = ts[TS_TANK]
    if h <= 0.0:
        tc[TC_EMPTY] += 1
    if tp[TP_ON] == 0.0:
        ts[TS_BETA] = 0.0
        return
    for j in range(6):
        if not (math.isfinite(cmd[j]) and math.isfinite(twist[j]) and math.isfinite(prev[j])):
            ts[TS_BETA] = beta_of(tp, h)
            return  # the safety filter faults on a non-finite command; a bad twist limits nothing
    period = tp[TP_PERIOD]
    h -= reserve(prev, 0, twist, hand, force_rate, period, tp[TP_MASS])
    h -= reserve(prev, 3, twist, hand, torque_rate, period, tp[TP_INERTIA])
    ts[TS_BETA] = beta_of(tp, h)
    half = 0.5 * allowance(tp, h)
    hit = _limit3(cmd, 0, twist, hand, half, period, tp[TP_MASS])
    if _limit3(cmd, 3, twist, hand, half, period, tp[TP_INERTIA]):
        hit = True
    if hit:
        tc[TC_LIMITED] += 1


def set_parameters(tp: np.ndarray, *, enabled: bool, initial_budget_j: float, max_tank_j: float, low_level_j: float,
                   moving_mass_kg: float, moving_inertia_kg_m2: float,
                   device_damping_n_s_per_m: float, device_rot_damping_n_m_s_per_rad: float, period_s: float,
                   engine_grants: bool = True, input_credit: float = 1.0) -> None:
    """``tp`` from named values (the ``[passivity]`` table's keys, the moving mass and inertia
    resolved: ``moving_figures``), each checked."""
    values = dict(initial_budget_j=initial_budget_j, max_tank_j=max_tank_j, low_level_j=low_level_j,
                  moving_mass_kg=moving_mass_kg, moving_inertia_kg_m2=moving_inertia_kg_m2,
                  device_damping_n_s_per_m=device_damping_n_s_per_m,
                  device_rot_damping_n_m_s_per_rad=device_rot_damping_n_m_s_per_rad, period_s=period_s)
    for name, v in values.items():
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"passivity.{name}: must be finite and >= 0, got {v!r}")
    for name in ("low_level_j", "moving_mass_kg", "moving_inertia_kg_m2", "period_s"):
        if values[name] <= 0.0:
            raise ValueError(f"passivity.{name}: must be > 0, got {values[name]!r}")
    if not (0.0 < input_credit <= 1.0):
        raise ValueError(f"passivity.input_credit: must be in (0, 1], got {input_credit!r}")
    if initial_budget_j > max_tank_j:
        raise ValueError(f"passivity.initial_budget_j: {initial_budget_j} J is more than max_tank_j {max_tank_j} J")
    tp[TP_ON] = 1.0 if enabled else 0.0
    tp[TP_H0] = initial_budget_j
    tp[TP_HMAX] = max_tank_j
    tp[TP_HLOW] = low_level_j
    tp[TP_MASS] = moving_mass_kg
    tp[TP_INERTIA] = moving_inertia_kg_m2
    tp[TP_BDEV] = device_damping_n_s_per_m
    tp[TP_BRDEV] = device_rot_damping_n_m_s_per_rad
    tp[TP_PERIOD] = period_s
    tp[TP_GRANTS] = 1.0 if engine_grants else 0.0
    tp[TP_CREDIT] = input_credit


#: what the prediction assumes for a device that states no moving mass or inertia (and a config
#: that sets none): lighter than the devices the project knows, so the zero-order-hold term is
#: over-estimated and the layer limits more, never less
FALLBACK_MASS_KG = 0.02
FALLBACK_INERTIA_KG_M2 = 1e-6


def moving_figures(config_mass_kg: float, config_inertia_kg_m2: float, info=None) -> tuple[float, float]:
    """The moving mass and smallest principal moment the prediction uses: the config's when set
    (> 0), else the device's stated figures (``DeviceInfo.moving_mass_kg`` /
    ``moving_inertia_kg_m2``), else ``FALLBACK_*``."""
    mass = config_mass_kg
    if not mass > 0.0:
        mass = getattr(info, "moving_mass_kg", None) or FALLBACK_MASS_KG
    inertia = config_inertia_kg_m2
    if not inertia > 0.0:
        inertia = getattr(info, "moving_inertia_kg_m2", None) or FALLBACK_INERTIA_KG_M2
    return float(mass), float(inertia)


def damping_figures(config_b: float, config_br: float, info=None, share: float = 1.0) -> tuple[float, float]:
    """The viscous damping whose dissipation feeds the tank (contract A2), N s/m and N m s/rad:
    the config's when set (> 0), else the device's stated figures (``DeviceInfo.damping_n_s_per_m``
    / ``rot_damping_n_m_s_per_rad``: a simulated device states its own), else 0 (nothing assumed).
    A figure above the device's true damping would credit energy it does not dissipate: a vendor's
    figure only, never a guess. Why it matters: a four-channel controller renders the proxy,
    which has no such damping, so in free motion the motor pays the device's damping along the
    motion (Fig. 14: +0.3 N at 0.25 m/s against 2 N s/m); uncredited, that drains the tank as if
    it were given to the hand (EXPERIMENTS.md, transparency).

    ``share`` (``[passivity] damping_credit``, 0..1) scales both: the knob between transparency (1:
    the damper's dissipation all credited, the free-motion payment above costs the tank nothing)
    and the renderable wall (0: the layer stops a limit cycle that the device's damper absorbs,
    as it stops one on an undamped device). Outside [0, 1] or non-finite: ``ValueError`` naming it."""
    if not (math.isfinite(share) and 0.0 <= share <= 1.0):
        raise ValueError(f"passivity.damping_credit: must be in [0, 1], got {share!r}")
    b = config_b if config_b > 0.0 else (getattr(info, "damping_n_s_per_m", None) or 0.0)
    br = config_br if config_br > 0.0 else (getattr(info, "rot_damping_n_m_s_per_rad", None) or 0.0)
    return float(b) * share, float(br) * share
