"""The passivity layer: an energy tank under the controller, as two small pure kernels.

The two-layer idea (Franken, Stramigioli et al., IEEE T-RO 2011): the controller above stays
what it is (transparency); below it, before the safety filter, a tank of energy decides how much
of the command may *give* energy to the hand. The tank is the running balance of the hand's
port (``control.port_energy``: each command held over a period times the handle's displacement
during it), so the server can never give the hand more than the tank held at the start, what
the hand put in, what the device's own damping dissipated and what an engine granted. Energy the
hand puts in and the controller's dampers then dissipate stays counted in the tank (it entered
the port and did not come back out): counting the coupling damper's dissipation on top would
count it twice. The device's physical damping is outside the port (the motor's work minus it is
what reaches the hand), so it feeds the tank: ``b |dx|^2 / T`` per period, the least a viscous
damper ``b`` dissipates over a displacement ``dx`` in ``T`` (Cauchy-Schwarz), with ``b`` as the
config declares it (0: nothing assumed).

Layouts (declared once; the controller embeds them as blocks of its arrays, ``CP_TANK``,
``CS_TANK``, ``CC_TANK``):

- ``tp`` parameters, float64[NTP]: ``TP_*`` below.
- ``ts`` state, float64[NTS]: the tank level and its books.
- ``tc`` counters, int64[NTC].

Contract of ``account(tp, ts, w_j, dx2_m2, dr2_rad2)`` (after the ledger paired the last period;
``w_j`` is the energy given to the hand over it, ``dx2_m2`` / ``dr2_rad2`` the squared
displacement and rotation of the handle during it):

A1. A non-finite ``w_j`` (or squared motion) changes nothing but the count ``TS_BAD``.
A2. Otherwise ``H1 = min(TP_HMAX, H0 - w_j + (TP_BDEV dx2 + TP_BRDEV dr2) / TP_PERIOD)``: the
    hand's energy drains it, what the hand puts in and the declared damping feed it, the cap
    bounds what a hand can store for later. ``TS_GIVEN`` / ``TS_TAKEN`` / ``TS_DAMPED`` add the
    positive part, the negative part of ``w_j`` and the damping's share.

``grant(tp, ts, e_j)``: an engine's declared work on the tool (``ContactUpdate.work_on_tool_j``)
is added like the hand's input (capped at ``TP_HMAX``); a negative or non-finite grant adds
nothing (the caller refuses it by name before).

Contract of ``limit(tp, ts, tc, cmd, twist)`` (``cmd`` the controller's wrench, device frame;
``twist`` the handle's twist, device frame; in place). Write ``f`` for the force, ``v`` for the
velocity (torque and angular velocity alike, with ``TP_W0`` for ``TP_V0``), ``p = f . v`` the
power the command gives the hand, ``H`` the tank level, ``L = TP_HLOW``:

L1. Off (``TP_ON == 0``) or ``H >= L``: the command is unchanged.
L2. The limiting factor ``beta`` is a smooth function of the level alone: 1 at ``H <= 0``, 0 at
    ``H >= L``, ``s^2 (3 - 2 s)`` with ``s = 1 - H / L`` between (C1: no step in the level's
    effect, the chatter a switched passivity controller has).
L3. What is removed: ``f' = f - beta (max(0, p) v + v0^2 f) / (|v|^2 + v0^2)``. Moving
    (``|v| >> v0``) that is the power-giving component along ``v`` (what is across ``v``, and a
    force that takes energy, stay); at rest (``|v| << v0``, where the direction the handle will
    move is not known yet) it is the whole force, scaled by ``1 - beta``. So ``|f' - f| <= beta
    |f|``; where ``p > 0``, ``0 <= f' . v = (1 - beta) p`` (never a pull: the layer never turns
    into a damper that takes energy); where ``p <= 0``, ``p <= f' . v <= 0``.
L4. Continuous in the command, the velocity and the level (no switch at ``p = 0`` or at
    ``v = 0``): ``|f'(v1) - f'(v2)| <= 2.5 beta |f| |v1 - v2| / v0`` for the same ``f`` and
    ``H``. The safety filter after the layer bounds every output step by its rate limit,
    whatever the layer asked.
L5. With the tank empty (``beta = 1``) the output gives no power at the sampled velocity
    (``f' . v <= 0``): what still reaches the hand is the motion within a period that the
    command itself causes (zero-order hold) and the safety filter's rate limit taking a period
    to follow; the margin ``L`` starts limiting before the tank is empty so that these are paid
    from it first.
L6. Finite in, finite out; ``tc[TC_LIMITED]`` counts calls that changed the command,
    ``tc[TC_EMPTY]`` calls with ``H <= 0``; ``TS_BETA`` keeps the factor used.

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
TP_HLOW = 3        # below this level the power-giving part is limited, J
TP_V0 = 4          # velocity below which the removed part fades (L4), m/s
TP_W0 = 5          # angular velocity alike, rad/s
TP_BDEV = 6        # the device's declared viscous damping, N s/m
TP_BRDEV = 7       # and rotational, N m s/rad
TP_PERIOD = 8      # the haptic period, s
TP_GRANTS = 9      # 1: engines' grants feed the tank
NTP = 10

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
    h = min(tp[TP_HMAX], ts[TS_TANK] - w_j + damped)
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
def _limit3(cmd, o, twist, beta, v0):
    """cmd[o:o+3] less ``beta (max(0, p) v + v0^2 f) / (|v|^2 + v0^2)`` with v = twist[o:o+3]
    (L3). True when the command changed."""
    vx = twist[o]; vy = twist[o + 1]; vz = twist[o + 2]
    p = cmd[o] * vx + cmd[o + 1] * vy + cmd[o + 2] * vz
    d = vx * vx + vy * vy + vz * vz + v0 * v0
    k = beta * max(p, 0.0) / d
    rest = 1.0 - beta * v0 * v0 / d
    hit = False
    for j in range(3):
        old = cmd[o + j]
        cmd[o + j] = old * rest - k * twist[o + j]
        if cmd[o + j] != old:
            hit = True
    return hit


@njit(**_JIT)
def limit(tp, ts, tc, cmd, twist):
    """The command's power-giving part limited by the tank (contract L1-L6), in place."""
    h = ts[TS_TANK]
    if h <= 0.0:
        tc[TC_EMPTY] += 1
    if tp[TP_ON] == 0.0:
        ts[TS_BETA] = 0.0
        return
    beta = beta_of(tp, h)
    ts[TS_BETA] = beta
    if beta == 0.0:
        return
    for j in range(6):
        if not (math.isfinite(cmd[j]) and math.isfinite(twist[j])):
            return  # the safety filter faults on a non-finite command; a bad twist limits nothing
    hit = _limit3(cmd, 0, twist, beta, tp[TP_V0])
    if _limit3(cmd, 3, twist, beta, tp[TP_W0]):
        hit = True
    if hit:
        tc[TC_LIMITED] += 1


def set_parameters(tp: np.ndarray, *, enabled: bool, initial_budget_j: float, max_tank_j: float, low_level_j: float,
                   velocity_threshold_m_per_s: float, angular_velocity_threshold_rad_per_s: float,
                   device_damping_n_s_per_m: float, device_rot_damping_n_m_s_per_rad: float, period_s: float,
                   engine_grants: bool = True) -> None:
    """``tp`` from named values (the ``[passivity]`` table's keys), each checked."""
    values = dict(initial_budget_j=initial_budget_j, max_tank_j=max_tank_j, low_level_j=low_level_j,
                  velocity_threshold_m_per_s=velocity_threshold_m_per_s,
                  angular_velocity_threshold_rad_per_s=angular_velocity_threshold_rad_per_s,
                  device_damping_n_s_per_m=device_damping_n_s_per_m,
                  device_rot_damping_n_m_s_per_rad=device_rot_damping_n_m_s_per_rad, period_s=period_s)
    for name, v in values.items():
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"passivity.{name}: must be finite and >= 0, got {v!r}")
    for name in ("low_level_j", "velocity_threshold_m_per_s", "angular_velocity_threshold_rad_per_s", "period_s"):
        if values[name] <= 0.0:
            raise ValueError(f"passivity.{name}: must be > 0, got {values[name]!r}")
    if initial_budget_j > max_tank_j:
        raise ValueError(f"passivity.initial_budget_j: {initial_budget_j} J is more than max_tank_j {max_tank_j} J")
    tp[TP_ON] = 1.0 if enabled else 0.0
    tp[TP_H0] = initial_budget_j
    tp[TP_HMAX] = max_tank_j
    tp[TP_HLOW] = low_level_j
    tp[TP_V0] = velocity_threshold_m_per_s
    tp[TP_W0] = angular_velocity_threshold_rad_per_s
    tp[TP_BDEV] = device_damping_n_s_per_m
    tp[TP_BRDEV] = device_rot_damping_n_m_s_per_rad
    tp[TP_PERIOD] = period_s
    tp[TP_GRANTS] = 1.0 if engine_grants else 0.0
