"""The stable region of the local contact model, as measured, and the bound the server keeps.

``hapticproxy experiment tradeoff`` (its stable-region part, ``experiments/tradeoff.py``
``stable_region``) sweeps, per controller and haptic rate, the contact stiffness from 1 kN/m to
1 MN/m with the paper's damping per stiffness (b = 7.5 ms x k), on the planar testbed with the
paper's 0.25 kg peg: a stiffness is stable when neither the wall push nor 6 s of Fig. 16's
shaking is unstable on any of three engine seeds. :data:`MEASURED` is its result before issue 31
(2026-11-22: the explicit step, no passivity layer; the ``largest_stable_stiffness_n_per_m`` of
``docs/experiments/tradeoff.json``; a test keeps the two equal, so re-running the sweep and
forgetting this table fails).

Re-measured with the server's current defaults (2026-12-05, ``hapticproxy experiment tradeoff
--region-only``: the implicit step, the layer on; ``docs/experiments/stable_region.json``), every
row's band reaches at least this table's value at every rate (a test checks it), so the bound is
kept as it was: inside the new region everywhere, conservative where the implicit step took the
explicit step's limit away (EXPERIMENTS.md "The stable region" says why it is not raised).

The rule (:func:`stable_contact_limits`):

- the row: the configured controller's (``four_channel``, ``coupler``, ``direct``), measured
  with the deformation policy; a policy without proxy deformation (``rigid``, ``lm0``, ``lm``)
  takes the smaller of that row and the IR row (direct, rigid: the only measured row without
  deformation, whose band does not grow with the rate);
- the rate: at a measured rate, its value; between two measured rates, the smaller of the two
  (the grid's largest stable stiffness is a lower bound of the true limit at that rate, so the
  smaller neighbour is a lower bound between them whenever the limit is monotone between grid
  points, rising or falling: no direction is assumed); below the lowest measured rate (256 Hz)
  the 256 Hz value scaled by (rate / 256)^2 (the explicit step's limit, k dt^2 / m bounded);
  above the highest (8 kHz), the 8 kHz value (never extrapolated upwards);
- damping: the rows were measured with b = 7.5 ms x k (``b_rule``), so the largest damping
  measured stable is ``b_rule x k_max``; more damping than that is outside the region too (the
  explicit step's other limit, b dt / m bounded).

The four-channel controller was also swept with b fixed at 30 N s/m
(:data:`MEASURED_FIXED_DAMPING`), stable to higher stiffness at 512 Hz and from 2 kHz up:
:func:`outside_stable_region` accepts k up to that row when b <= 30 N s/m.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..protocol.vocab import CONTROLLERS, POLICIES  # noqa: F401 - the vocabulary, once

#: b = DAMPING_PER_STIFFNESS_S x k: the damping the rows were measured with (the paper's 30 N s/m
#: at 4000 N/m); ``experiments/tradeoff.py`` DAMPING_PER_STIFFNESS_S.
DAMPING_PER_STIFFNESS_S = 0.0075
#: Haptic rates of the sweep [Hz].
RATES_HZ = (256.0, 512.0, 1000.0, 2000.0, 4000.0, 8000.0)
#: Largest stable contact stiffness [N/m] per row and rate (``RATES_HZ``), b = 7.5 ms x k.
MEASURED: dict[str, tuple[float, ...]] = {
    "four_channel": (4000.0, 10000.0, 50000.0, 100000.0, 200000.0, 500000.0),
    "coupler": (4000.0, 10000.0, 50000.0, 100000.0, 200000.0, 500000.0),
    "direct": (10000.0, 20000.0, 50000.0, 100000.0, 200000.0, 500000.0),
    "IR (direct, rigid, eps 0, eq. 1)": (10000.0, 20000.0, 10000.0, 10000.0, 10000.0, 10000.0),
}
#: The same sweep's row names in ``tradeoff.json`` for the fixed-damping family.
FIXED_DAMPING_ROW = "four_channel, b = 30 N s/m"
FIXED_DAMPING_N_S_PER_M = 30.0
#: Largest stable stiffness [N/m] of the four-channel controller with b = 30 N s/m.
MEASURED_FIXED_DAMPING: tuple[float, ...] = (4000.0, 20000.0, 50000.0, 200000.0, 1000000.0, 1000000.0)
IR_ROW = "IR (direct, rigid, eps 0, eq. 1)"
#: One haptic step's force change at most this unless overridden (``safety.force_rate_n_per_s``).
MAX_FORCE_STEP_N = 1.0


class StableContactLimits(NamedTuple):
    """``k_max_n_per_m``: the largest contact stiffness inside the measured region;
    ``b_rule_s``: the damping per stiffness it was measured with (b = b_rule_s x k)."""

    k_max_n_per_m: float
    b_rule_s: float

    @property
    def b_max_n_s_per_m(self) -> float:
        """The largest damping measured stable at this rate: b_rule x k_max."""
        return self.b_rule_s * self.k_max_n_per_m


def _at_rate(row: tuple[float, ...], rate_hz: float) -> float:
    lo_r = RATES_HZ[0]
    if rate_hz <= lo_r:
        return row[0] * (rate_hz / lo_r) ** 2
    if rate_hz >= RATES_HZ[-1]:
        return row[-1]
    for i, r in enumerate(RATES_HZ):
        if rate_hz == r:
            return row[i]
        if rate_hz < r:
            return min(row[i - 1], row[i])
    raise AssertionError("unreachable")


def _check(rate_hz: float, controller: str, policy: str) -> None:
    if not (isinstance(rate_hz, (int, float)) and rate_hz > 0 and rate_hz < float("inf")):
        raise ValueError(f"rate_hz: expected a positive finite rate, got {rate_hz!r}")
    if controller not in CONTROLLERS:
        raise ValueError(f"controller: expected one of {', '.join(CONTROLLERS)}; got {controller!r}")
    if policy not in POLICIES:
        raise ValueError(f"policy: expected one of {', '.join(POLICIES)}; got {policy!r}")


def stable_contact_limits(rate_hz: float, controller: str, policy: str = "deformation") -> StableContactLimits:
    """The measured stable region's bound for a haptic rate, controller and update policy:
    ``(k_max, b_rule)`` with b = b_rule x k the damping rule it holds for (module docstring)."""
    _check(rate_hz, controller, policy)
    k = _at_rate(MEASURED[controller], float(rate_hz))
    if policy != "deformation":
        k = min(k, _at_rate(MEASURED[IR_ROW], float(rate_hz)))
    return StableContactLimits(k, DAMPING_PER_STIFFNESS_S)


def fixed_damping_k_max(rate_hz: float, controller: str, policy: str = "deformation") -> float | None:
    """k_max of the fixed-damping family (b <= 30 N s/m), where it was measured (four-channel,
    deformation policy); None elsewhere."""
    _check(rate_hz, controller, policy)
    if controller != "four_channel" or policy != "deformation":
        return None
    return _at_rate(MEASURED_FIXED_DAMPING, float(rate_hz))


def max_force_rate_n_per_s(rate_hz: float) -> float:
    """The force-rate limit at which one haptic step changes the force by at most 1 N."""
    return MAX_FORCE_STEP_N * float(rate_hz)


#: k dt^2 / m at most this for a spring acting on the device's own mass, explicitly integrated at
#: the haptic rate (the simulated device keeps its end-stops to the same rule: ``sim.ENDSTOP_STABILITY``)
DEVICE_SPRING_STABILITY = 2.0


def device_spring_limit_n_per_m(mass_kg: float, rate_hz: float) -> float:
    """The stiffest spring the device's own mass takes at this rate: 2 m rate^2."""
    return DEVICE_SPRING_STABILITY * float(mass_kg) * float(rate_hz) ** 2


#: B dt / m at most this for a damper acting on the device's own mass (half the explicit step's
#: bound of 2, the margin the spring's bound keeps of its 4)
DEVICE_DAMPER_STABILITY = 1.0
#: the rate the devices' stiffness and damping figures are stated at (CHAI3D's ``cHapticDeviceInfo``,
#: OpenHaptics' ``HD_NOMINAL_*``: what the device renders stably in a 1 kHz servo loop) [Hz]
DEVICE_FIGURES_RATE_HZ = 1000.0


def device_damper_limit_n_s_per_m(mass_kg: float, rate_hz: float) -> float:
    """The most damping the device's own mass takes at this rate: m rate."""
    return DEVICE_DAMPER_STABILITY * float(mass_kg) * float(rate_hz)


def device_stiffness_at_rate(k_at_1khz: float, rate_hz: float) -> float:
    """A device's stiffness figure (stated at 1 kHz) at another rate, by Colgate and Schenkel's
    passivity bound for a sampled spring K and damper B on a device with physical damping b,
    ``K < 2 (b - |B|) / T``: the device's b fixed, the stiffest spring grows with the rate,
    ``K(rate) = K(1 kHz) rate / 1 kHz`` (and shrinks below it)."""
    return float(k_at_1khz) * float(rate_hz) / DEVICE_FIGURES_RATE_HZ


def above_device_limits(*, rate_hz: float, controller: str, device_mass_kg: float | None, stiffness_n_per_m: float,
                        coupling_stiffness_n_per_m: float) -> list[tuple[str, str]]:
    """Springs stiffer than the device's mass takes at this rate (the device's own limit): the
    coupling spring of the four-channel and coupler controllers, or, with direct coupling (the
    device is the tool), the contact stiffness. ``device_mass_kg`` None: the driver does not say."""
    if device_mass_kg is None:
        return []
    k_dev = device_spring_limit_n_per_m(device_mass_kg, rate_hz)
    key, k = (("model.stiffness_n_per_m", stiffness_n_per_m) if controller == "direct"
              else ("controller.stiffness_n_per_m", coupling_stiffness_n_per_m))
    if k <= k_dev:
        return []
    return [(key, f"{k:g} N/m on the device's {device_mass_kg:g} kg at {rate_hz:g} Hz is beyond what the haptic step "
                  f"integrates stably (k dt^2 / m <= {DEVICE_SPRING_STABILITY:g}, the device's own limit); "
                  f"nearest safe value {k_dev:.6g}")]


def outside_stable_region(*, rate_hz: float, controller: str, policy: str, stiffness_n_per_m: float,
                          damping_n_s_per_m: float, force_rate_n_per_s: float) -> list[tuple[str, str]]:
    """Every setting outside the measured region, as ``(key, reason with the nearest safe value)``."""
    out: list[tuple[str, str]] = []
    lim = stable_contact_limits(rate_hz, controller, policy)
    k_fixed = fixed_damping_k_max(rate_hz, controller, policy)
    where = f"{controller} controller, {policy} policy, at {rate_hz:g} Hz"
    src = "(hapticproxy experiment tradeoff, EXPERIMENTS.md 'The stable region')"
    k, b = stiffness_n_per_m, damping_n_s_per_m
    k_ok = lim.k_max_n_per_m
    if k_fixed is not None and b <= FIXED_DAMPING_N_S_PER_M:
        k_ok = max(k_ok, k_fixed)
    if k > k_ok:
        fam = (f"with b <= {FIXED_DAMPING_N_S_PER_M:g} N s/m" if k_ok != lim.k_max_n_per_m
               else f"with b = {lim.b_rule_s * 1e3:g} ms x k")
        out.append(("model.stiffness_n_per_m",
                    f"{k:g} N/m is outside the stable region measured for the {where}: stable up to "
                    f"{k_ok:g} N/m {fam} {src}; nearest safe value {k_ok:g}"))
    b_max = lim.b_max_n_s_per_m
    if b > b_max:
        out.append(("model.damping_n_s_per_m",
                    f"{b:g} N s/m is more damping than the stable region measured for the {where} "
                    f"(b = {lim.b_rule_s * 1e3:g} ms x k up to k = {lim.k_max_n_per_m:g} N/m) {src}; "
                    f"nearest safe value {b_max:g}"))
    f_max = max_force_rate_n_per_s(rate_hz)
    if force_rate_n_per_s > f_max:
        out.append(("safety.force_rate_n_per_s",
                    f"{force_rate_n_per_s:g} N/s lets one step at {rate_hz:g} Hz change the force by "
                    f"{force_rate_n_per_s / rate_hz:.4g} N (at most {MAX_FORCE_STEP_N:g} N); nearest safe value {f_max:g}"))
    return out


# --------------------------------------------------------------------------- heavy tools at rest
#: the coupling's damping is set this many times the smallest that keeps the rest loop stable
#: (:func:`coupling_damping_for_tool`): at 1x the slowest mode only just stops growing and a landing's
#: bounce would ring for ever; at 1.5x a 2 kg tool's slowest mode decays at 5.3 /s on the simulated
#: planar device, 6.7 /s on the spatial one, 9.3 /s on the 1dof one (1 to 32 contacts)
HEAVY_TOOL_MARGIN = 1.5
#: the search for the smallest damping: doubling from 1 N s/m up to 1e5 (the config's key goes to
#: 1e4), then bisecting the last doubling to within this share of it (about 20 checks in all)
_B_SEARCH_MAX = 1e5
_B_SEARCH_REL = 1e-4


def rest_loop_coefficients(tool_mass_kg, device_mass_kg, device_damping_n_s_per_m, contact_n_per_m,
                           contact_n_s_per_m, coupling_n_per_m, coupling_n_s_per_m, env_gain=1.0):
    """The characteristic polynomial ``a4 s^4 + a3 s^3 + a2 s^2 + a1 s + a0`` of the four-channel
    loop at rest on its contacts, along their normal (:func:`rest_loop_stable`); numpy arrays
    broadcast (one per contact count, say). Returns ``(a4, a3, a2, a1, a0)``."""
    mp, md, bd = tool_mass_kg, device_mass_kg, device_damping_n_s_per_m
    ke, be, kc, bc, g = contact_n_per_m, contact_n_s_per_m, coupling_n_per_m, coupling_n_s_per_m, env_gain
    a4 = mp * md
    a3 = mp * (bc + bd) + md * (be + bc)
    a2 = mp * kc + md * (ke + kc) + (1.0 + g) * be * bc + bd * (be + bc)
    a1 = (1.0 + g) * (be * kc + ke * bc) + bd * (ke + kc)
    a0 = (1.0 + g) * ke * kc
    return a4, a3, a2, a1, a0


def rest_loop_stable(tool_mass_kg: float, *, device_mass_kg: float, device_damping_n_s_per_m: float,
                     contact_n_per_m: float, contact_n_s_per_m: float, max_contacts: int, coupling_n_per_m: float,
                     coupling_n_s_per_m: float, env_gain: float = 1.0, contact_scales=None) -> bool:
    """Whether the four-channel loop at rest is stable on every number of contacts from 1 to
    ``max_contacts`` (each ``contact_n_per_m``, ``contact_n_s_per_m``), as a continuous system
    (``contact_scales``: the multiples of one contact to check instead of 1..max_contacts).

    The loop (``experiments/lighttools.py`` ``rest_growth_per_s``, EXPERIMENTS.md "Why the heavy
    planar tool bounces"): along the contacts' normal, the proxy m_p on the n contacts (k_e = n k,
    b_e = n b) and the coupling (k_c, b_c) to the handle (m_d, its damping b_d); the handle is
    rendered g times the contacts' force less the coupling's; the hand's push is constant::

        m_p x_p'' = -k_e x_p - b_e x_p' + k_c (x_d - x_p) + b_c (x_d' - x_p')
        m_d x_d'' = -g (k_e x_p + b_e x_p') - k_c (x_d - x_p) - b_c (x_d' - x_p') - b_d x_d'

    Its characteristic polynomial det(s^2 M + s B + K) (:func:`rest_loop_coefficients`)::

        a4 = m_p m_d
        a3 = m_p (b_c + b_d) + m_d (b_e + b_c)
        a2 = m_p k_c + m_d (k_e + k_c) + (1 + g) b_e b_c + b_d (b_e + b_c)
        a1 = (1 + g) (b_e k_c + k_e b_c) + b_d (k_e + k_c)
        a0 = (1 + g) k_e k_c

    By Routh and Hurwitz its roots all have negative real parts iff every a_i > 0 and
    ``a3 a2 a1 - a4 a1^2 - a3^2 a0 > 0`` (which with them implies a3 a2 > a4 a1): the same verdict
    as the eigenvalues' largest real part (``rest_growth_per_s`` < 0), in a few array operations.
    Why it fails for heavy tools: the proxy on its contacts (sqrt((k_e + k_c) / m_p)) and the
    handle on the coupling (sqrt(k_c / m_d)) are two resonators coupled one way much more strongly
    than the other (the handle is given g k_e x_p, the proxy k_c x_d); where their frequencies
    meet, m_p near m_d (k_e + k_c) / k_c, that non-reciprocal coupling feeds a mode faster than the
    dampers drain it, unless b_c is large enough. As n grows the mass where they meet grows with it
    (1.7-2.5 kg on one contact on the planar device, 17-140 kg on 32), but the polynomial divided
    by n tends to a limit, so the damping needed stays bounded over every mass and count."""
    n = (np.arange(1, int(max_contacts) + 1, dtype=np.float64) if contact_scales is None
         else np.asarray(contact_scales, dtype=np.float64))
    a4, a3, a2, a1, a0 = rest_loop_coefficients(float(tool_mass_kg), float(device_mass_kg),
                                                float(device_damping_n_s_per_m), n * float(contact_n_per_m),
                                                n * float(contact_n_s_per_m), float(coupling_n_per_m),
                                                float(coupling_n_s_per_m), float(env_gain))
    hurwitz = a3 * a2 * a1 - a4 * a1 * a1 - a3 * a3 * a0
    return bool(np.all((a4 > 0) & (a3 > 0) & (a2 > 0) & (a1 > 0) & (a0 > 0) & (hurwitz > 0)))


def least_rest_damping_n_s_per_m(tool_mass_kg: float, start: float = 1.0, **loop) -> float | None:
    """The smallest coupling damping b_c at which :func:`rest_loop_stable` holds (``loop``: its
    keyword arguments but ``coupling_n_s_per_m``); 0 when the loop is stable undamped, None when
    not even ``_B_SEARCH_MAX`` is; within ``_B_SEARCH_REL`` of it (or of ``start``, if more), on the
    stable side. Doubling
    from ``start`` (1 N s/m) to the first stable value, then bisecting the last doubling: above the smallest,
    every damping is stable too (checked by the property tests, ``tests/server/test_heavy_tools.py``,
    up to 20x the rule's)."""
    def ok(b: float) -> bool:
        return rest_loop_stable(tool_mass_kg, coupling_n_s_per_m=b, **loop)

    if ok(0.0):
        return 0.0
    lo, hi = 0.0, float(start)
    while not ok(hi):
        if hi >= _B_SEARCH_MAX:
            return None
        lo, hi = hi, min(2.0 * hi, _B_SEARCH_MAX)
    while hi - lo > _B_SEARCH_REL * max(hi, start):
        mid = 0.5 * (lo + hi)
        if ok(mid):
            hi = mid
        else:
            lo = mid
    return hi


def coupling_damping_for_tool(tool_mass_kg: float, *, device_mass_kg: float | None, device_damping_n_s_per_m: float,
                              contact_n_per_m: float, contact_n_s_per_m: float, max_contacts: int,
                              coupling_n_per_m: float, coupling_n_s_per_m: float, env_gain: float = 1.0) -> float | None:
    """The coupling's translational damping for a session's tool: the configured
    ``coupling_n_s_per_m``, raised to ``HEAVY_TOOL_MARGIN`` times the least damping that keeps the
    four-channel loop at rest stable (:func:`least_rest_damping_n_s_per_m`, on 1 to
    ``max_contacts`` contacts) where that is more::

        b_c = max(b_configured, HEAVY_TOOL_MARGIN x b_least(m_p, m_d, b_d, k, b, N, k_c, g))

    Light tools keep the configured damping (with the default contacts, coupling and capacity
    and no device damping assumed: every tool up to 0.79 kg on the simulated spatial device, 0.83
    kg on the planar one, 1.09 kg on the 1dof one), so what they render does not change; a heavy
    one gets at most 42.1 N s/m on the planar device (at 55 kg; 27.7 at 2 kg), 32.2 on the
    spatial one, 22.3 on the 1dof one (42.4, 32.4, 22.4 with 64 contacts). The handle's
    stated mass is needed (None: not stated, the configured damping is returned); its damping
    ``device_damping_n_s_per_m`` only helps (0, nothing assumed, is the safe side). Returns None
    when no damping up to the search's end makes the loop stable (the tool is to be refused)."""
    b0 = float(coupling_n_s_per_m)
    if device_mass_kg is None or not device_mass_kg > 0.0:
        return b0
    least = least_rest_damping_n_s_per_m(
        tool_mass_kg, device_mass_kg=device_mass_kg, device_damping_n_s_per_m=device_damping_n_s_per_m,
        contact_n_per_m=contact_n_per_m, contact_n_s_per_m=contact_n_s_per_m, max_contacts=max_contacts,
        coupling_n_per_m=coupling_n_per_m, env_gain=env_gain)
    if least is None:
        return None
    return max(b0, HEAVY_TOOL_MARGIN * least)


#: the rotational contacts' stiffness about the hand point, sum k r_i^2, as multiples of the
#: coupling's rotational spring: the lever arms are the tool's geometry, which the server does not
#: know, so every value from 1e-3 to 1e6 of it is checked (the unstable band sits where the tool's
#: turn on its contacts meets the handle's on the coupling; the damping it needs stays bounded as
#: the stiffness grows, as the translation's does with the contact count)
ROT_CONTACT_SCALES = np.geomspace(1e-3, 1e6, 400)


def rot_coupling_damping_for_tool(moments_kg_m2, *, device_inertia_kg_m2: float | None,
                                  device_rot_damping_n_m_s_per_rad: float, contact_damping_per_stiffness_s: float,
                                  coupling_n_m_per_rad: float, coupling_n_m_s_per_rad: float,
                                  env_gain: float = 1.0) -> float | None:
    """The coupling's rotational damping for a session's tool: :func:`coupling_damping_for_tool`'s
    rule about each of the tool's principal ``moments_kg_m2`` (a planar tool's I_zz alone), the
    largest. The same loop turned: the proxy's moment I_p on its contacts' rotational stiffness
    K = sum k r_i^2 and damping (b / k) K (the contacts' time constant
    ``contact_damping_per_stiffness_s``), the coupling's rotational spring and damper to the
    handle's moment I_d (``device_inertia_kg_m2``, the device's stated smallest: the moving
    inertia's figure) and damping; K over :data:`ROT_CONTACT_SCALES` x the coupling's spring, since
    the lever arms are not known. A moment below the handle's meets no resonance and keeps the
    configured damping (on the simulated planar device, I_d = 1e-3: up to 1e-3 kg m^2; a 2 kg rod of
    150 mm, 3.75e-3, gets 0.060 N m s/rad, the most any moment gets there is 0.103). None stated:
    the configured damping; None returned: no damping steadies it."""
    b0 = float(coupling_n_m_s_per_rad)
    if device_inertia_kg_m2 is None or not device_inertia_kg_m2 > 0.0:
        return b0
    out = b0
    for ip in moments_kg_m2:
        least = least_rest_damping_n_s_per_m(
            float(ip), device_mass_kg=float(device_inertia_kg_m2), device_damping_n_s_per_m=device_rot_damping_n_m_s_per_rad,
            contact_n_per_m=float(coupling_n_m_per_rad),
            contact_n_s_per_m=float(contact_damping_per_stiffness_s) * float(coupling_n_m_per_rad), max_contacts=0,
            coupling_n_per_m=coupling_n_m_per_rad, env_gain=env_gain, contact_scales=ROT_CONTACT_SCALES,
            start=max(b0, 1e-6))
        if least is None:
            return None
        out = max(out, HEAVY_TOOL_MARGIN * least)
    return out
