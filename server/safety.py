"""The safety filter: the last thing between the controller and the device, as one pure kernel.

``safety_filter(sp, ss, sc, cmd)`` turns the controller's wrench into the wrench written to the
device. It is the only code that decides how much force a hand can be given; everything above it
(controllers, the model, the protocol) may be wrong, and the filter's promises still hold.

Layouts (declared here once; the controller embeds them, ``control.Controller`` owns the arrays):

- ``sp`` parameters, float64[NSP]: ``SP_*`` below.
- ``ss`` state, float64[NSS]: the gain, its target, the previous output (what the device renders
  now), the periods skipped since the last call.
- ``sc`` counters, int64[NSC].
- ``cmd`` float64[6]: in, the controller's wrench ``fx fy fz`` [N], ``tx ty tz`` [N m], device
  frame at the handle; out, the wrench to write.

Contract. Write ``w`` for the output and ``p`` for the previous output (``ss[SS_PREV:]`` before
the call), ``f``/``t`` for a wrench's force and torque 3-vectors, ``|.|`` for the Euclidean norm,
``g0`` and ``g1`` for the gain before and after the call, ``n = 1 + skipped`` for the periods the
call accounts for. With the state consistent (``|p_f| <= g0 F``, ``|p_t| <= g0 T``; true from
``reset`` on, and kept by every call):

1. **Finite.** A non-finite component of ``cmd`` gives ``w = 0``, ``g1 = 0``, target 0, ``p = 0``
   and returns ``RC_NONFINITE`` (the caller disables the device). Otherwise ``w`` is finite and
   the call returns ``RC_OK``.
2. **Gain.** ``g1`` moves from ``g0`` towards the target by at most ``n * SP_RAMP`` up or
   ``n * SP_FADE`` down and never passes it (skipped periods count: a fade reaches zero in
   ``fade_s`` of wall-clock time). ``0 <= g1 <= 1``.
3. **Components.** ``w_j = 0`` wherever ``SP_MASK + j`` is 0 (what the device kind cannot render).
4. **Caps, on the norm and per axis.** ``|w_f| <= g1 F`` and ``|w_t| <= g1 T`` (``F = SP_FMAX``,
   ``T = SP_TMAX``); ``|w_fj| <= g1 Fa`` and ``|w_tj| <= g1 Ta`` per component (``SP_FAXIS``,
   ``SP_TAXIS``: a motor's own limit). So a 1-DOF device on a diagonal axis, or a spatial one
   pushed along a diagonal, gets at most ``F``, not ``sqrt(3) F``.
5. **Rate.** While the gain does not fall (``g1 >= g0``): ``|w_f - p_f| <= SP_FRATE`` and
   ``|w_t - p_t| <= SP_TRATE``, per call, however many periods were skipped (force never comes
   back as a step, also after a stall).
6. **Ramp envelope.** While the gain rises (``g1 > g0``): ``|w_f| <= |p_f| + F * SP_RAMP`` and
   ``|w_t| <= |p_t| + T * SP_RAMP`` per call, and per component ``|w_fj| <= |p_fj| + Fa *
   SP_RAMP`` (``Ta`` for torque): force comes back at the ramp's slope at most, along every axis,
   also when it resumes an interrupted fade.
7. **Fade envelope.** While the gain falls (``g1 < g0``), every component stays between zero and
   its previous value scaled like the gain: ``0 <= w_j / p_j <= g1 / g0`` (``w_j = 0`` where
   ``p_j = 0``). A hand that keeps pushing during a fade raises the controller's command, but never
   the output: a fade only takes force away, at least as fast as the gain falls. It may take it
   away faster than the rate limit only by what the gain itself drops:
   ``|w_f - p_f| <= SP_FRATE + (1 - g1/g0) |p_f|`` (and the same for torque).
8. **Zero gain, zero force.** ``g1 = 0`` gives ``w = 0`` (from a consistent state).

``reset(ss)`` (the device was disabled: it renders nothing now) sets ``p = 0``, the gain and its
target to 0. ``sc[SC_SATURATED]`` counts calls in which a cap changed the command,
``sc[SC_RATE_LIMITED]`` calls in which the rate limit did, ``sc[SC_NONFINITE]`` non-finite calls.

The order inside: mask, caps on the command (norm, then per axis), the gain, the ramp or fade
envelope, the rate limit from ``p``, and while fading the envelope once more (the rate limit
only ever moves towards a target that obeys it, but may stop short of it). Every bound is a
convex set containing ``p`` or the target, which is why the later steps never undo the earlier
ones (``tests/server/test_safety_filter.py`` checks every promise over random sequences).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_JIT = dict(cache=True, nogil=True, error_model="numpy")

# ---- parameters (float64[NSP])
SP_FMAX = 0        # force cap on the norm, N
SP_TMAX = 1        # torque cap on the norm, N m
SP_FAXIS = 2       # force cap per axis (a motor's own limit), N
SP_TAXIS = 3       # torque cap per axis, N m
SP_FRATE = 4       # largest change of the force vector per call, N
SP_TRATE = 5       # largest change of the torque vector per call, N m
SP_FADE = 6        # gain decrement per period (period / fade_s)
SP_RAMP = 7        # gain increment per period (period / ramp_in_s)
SP_MASK = 8        # 8..13: 1 where the device renders the component fx fy fz tx ty tz, else 0
NSP = 14

# ---- state (float64[NSS])
SS_GAIN = 0        # 0..1
SS_TARGET = 1      # where the gain goes: 1 rendering, 0 fading out
SS_PREV = 2        # 2..7 the last output (what the device renders)
SS_SKIPPED = 8     # periods skipped since the last call (the loop woke late); the call clears it
NSS = 9

# ---- counters (int64[NSC])
SC_SATURATED = 0
SC_RATE_LIMITED = 1
SC_NONFINITE = 2
NSC = 3

RC_OK = 0
RC_NONFINITE = 1


@njit(**_JIT)
def reset(ss):
    """The device renders nothing now (disabled, or never armed): no previous output, no gain."""
    for k in range(6):
        ss[SS_PREV + k] = 0.0
    ss[SS_GAIN] = 0.0
    ss[SS_TARGET] = 0.0
    ss[SS_SKIPPED] = 0.0


@njit(**_JIT)
def _norm3(v, o):
    return math.sqrt(v[o] * v[o] + v[o + 1] * v[o + 1] + v[o + 2] * v[o + 2])


@njit(**_JIT)
def _scale3(v, o, s):
    v[o] *= s
    v[o + 1] *= s
    v[o + 2] *= s


@njit(**_JIT)
def _caps(cmd, o, cap, cap_axis):
    """The norm cap, then the per-axis cap, on cmd[o:o+3]. True when either changed it."""
    hit = False
    n = _norm3(cmd, o)
    if n > cap:
        _scale3(cmd, o, cap / n)
        hit = True
    for j in range(o, o + 3):
        if cmd[j] > cap_axis:
            cmd[j] = cap_axis
            hit = True
        elif cmd[j] < -cap_axis:
            cmd[j] = -cap_axis
            hit = True
    return hit


@njit(**_JIT)
def _fade_envelope(cmd, ss, o, shrink):
    """Each component of cmd[o:o+3] between zero and the previous one times ``shrink``."""
    for j in range(o, o + 3):
        bound = ss[SS_PREV + j] * shrink
        if bound >= 0.0:
            cmd[j] = min(max(cmd[j], 0.0), bound)
        else:
            cmd[j] = max(min(cmd[j], 0.0), bound)


@njit(**_JIT)
def _ramp_envelope(cmd, ss, o, step, step_axis):
    """cmd[o:o+3] no longer (norm) than the previous output's plus ``step``, and no component
    larger than the previous one's plus ``step_axis`` (a force that turns while it ramps in
    does not grow faster along any axis either)."""
    grow = _norm3(ss, SS_PREV + o) + step
    n = _norm3(cmd, o)
    if n > grow:
        _scale3(cmd, o, grow / n)
    for j in range(o, o + 3):
        lim = abs(ss[SS_PREV + j]) + step_axis
        if cmd[j] > lim:
            cmd[j] = lim
        elif cmd[j] < -lim:
            cmd[j] = -lim


@njit(**_JIT)
def _rate(cmd, ss, o, rate):
    """cmd[o:o+3] at most ``rate`` (norm) from the previous output. True when it was moved."""
    dx = cmd[o] - ss[SS_PREV + o]
    dy = cmd[o + 1] - ss[SS_PREV + o + 1]
    dz = cmd[o + 2] - ss[SS_PREV + o + 2]
    d = math.sqrt(dx * dx + dy * dy + dz * dz)
    if d <= rate:
        return False
    s = rate / d
    cmd[o] = ss[SS_PREV + o] + dx * s
    cmd[o + 1] = ss[SS_PREV + o + 1] + dy * s
    cmd[o + 2] = ss[SS_PREV + o + 2] + dz * s
    return True


@njit(**_JIT)
def safety_filter(sp, ss, sc, cmd):
    """The wrench to write for the controller's ``cmd`` (in place). The module docstring is the
    contract. Returns ``RC_OK`` or ``RC_NONFINITE``."""
    for j in range(6):
        if not math.isfinite(cmd[j]):
            for k in range(6):
                cmd[k] = 0.0
            reset(ss)
            sc[SC_NONFINITE] += 1
            return RC_NONFINITE
    g0 = ss[SS_GAIN]
    g1 = g0
    periods = 1.0 + ss[SS_SKIPPED]
    ss[SS_SKIPPED] = 0.0
    target = ss[SS_TARGET]
    if target > g0:
        g1 = min(target, g0 + periods * sp[SP_RAMP])
    elif target < g0:
        g1 = max(target, g0 - periods * sp[SP_FADE])
    g1 = min(max(g1, 0.0), 1.0)
    ss[SS_GAIN] = g1
    for j in range(6):
        cmd[j] *= sp[SP_MASK + j]
    sat = _caps(cmd, 0, sp[SP_FMAX], sp[SP_FAXIS])
    if _caps(cmd, 3, sp[SP_TMAX], sp[SP_TAXIS]):
        sat = True
    for j in range(6):
        cmd[j] *= g1
    fading = g1 < g0
    shrink = 1.0
    if fading:
        shrink = g1 / g0
        _fade_envelope(cmd, ss, 0, shrink)
        _fade_envelope(cmd, ss, 3, shrink)
    elif g1 > g0:
        _ramp_envelope(cmd, ss, 0, sp[SP_FMAX] * sp[SP_RAMP], sp[SP_FAXIS] * sp[SP_RAMP])
        _ramp_envelope(cmd, ss, 3, sp[SP_TMAX] * sp[SP_RAMP], sp[SP_TAXIS] * sp[SP_RAMP])
    lim = _rate(cmd, ss, 0, sp[SP_FRATE])
    if _rate(cmd, ss, 3, sp[SP_TRATE]):
        lim = True
    if fading:
        _fade_envelope(cmd, ss, 0, shrink)
        _fade_envelope(cmd, ss, 3, shrink)
    for j in range(6):
        ss[SS_PREV + j] = cmd[j]
    if sat:
        sc[SC_SATURATED] += 1
    if lim:
        sc[SC_RATE_LIMITED] += 1
    return RC_OK


def parameters(*, max_force_n: float, max_torque_n_m: float, force_rate_n_per_step: float,
               torque_rate_n_m_per_step: float, fade_per_step: float, ramp_per_step: float, mask,
               max_force_axis_n: float | None = None, max_torque_axis_n_m: float | None = None) -> np.ndarray:
    """``sp`` from named values (the per-axis caps default to the norm caps: no tighter motor)."""
    sp = np.zeros(NSP)
    set_parameters(sp, max_force_n=max_force_n, max_torque_n_m=max_torque_n_m,
                   force_rate_n_per_step=force_rate_n_per_step, torque_rate_n_m_per_step=torque_rate_n_m_per_step,
                   fade_per_step=fade_per_step, ramp_per_step=ramp_per_step, mask=mask,
                   max_force_axis_n=max_force_axis_n, max_torque_axis_n_m=max_torque_axis_n_m)
    return sp


def set_parameters(sp: np.ndarray, *, max_force_n: float, max_torque_n_m: float, force_rate_n_per_step: float,
                   torque_rate_n_m_per_step: float, fade_per_step: float, ramp_per_step: float, mask,
                   max_force_axis_n: float | None = None, max_torque_axis_n_m: float | None = None) -> None:
    values = dict(max_force_n=max_force_n, max_torque_n_m=max_torque_n_m, force_rate_n_per_step=force_rate_n_per_step,
                  torque_rate_n_m_per_step=torque_rate_n_m_per_step, fade_per_step=fade_per_step,
                  ramp_per_step=ramp_per_step)
    for name, v in values.items():
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"safety filter: {name} must be finite and >= 0, got {v!r}")
    sp[SP_FMAX] = max_force_n
    sp[SP_TMAX] = max_torque_n_m
    sp[SP_FAXIS] = max_force_n if max_force_axis_n is None else min(max_force_n, max_force_axis_n)
    sp[SP_TAXIS] = max_torque_n_m if max_torque_axis_n_m is None else min(max_torque_n_m, max_torque_axis_n_m)
    sp[SP_FRATE] = force_rate_n_per_step
    sp[SP_TRATE] = torque_rate_n_m_per_step
    sp[SP_FADE] = fade_per_step
    sp[SP_RAMP] = ramp_per_step
    sp[SP_MASK:SP_MASK + 6] = [1.0 if m else 0.0 for m in mask]
