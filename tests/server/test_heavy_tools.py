"""Heavy tools at rest (issue 31 item 1's measure, "tools from 5 g to 2 kg ... at rest on a floor"):
the coupling's damping a session's tool gets (``stability.coupling_damping_for_tool``, set at
engagement by ``control.Controller.fit_tool``) keeps the four-channel loop at rest on its
contacts stable, on the simulated devices, for any tool mass and 1 to 64 contacts. The verdicts
are the eigenvalues' (``experiments/lighttools.py`` ``rest_growth_per_s``), independent of the
rule's Routh-Hurwitz test. Through the whole server: ``tests/experiments/test_lighttools.py``."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from hapticproxy.experiments.lighttools import rest_growth_per_s
from hapticproxy.server import config as cfg
from hapticproxy.server import control as ctl
from hapticproxy.server import stability as sb
from hapticproxy.server.devices.sim import effective_config, make_sim_device
from hapticproxy.server.model import LinkSpec, ToolSpec

#: the simulated devices' handles (mass kg, damping N s/m): ``devices/sim.py``'s defaults
DEVICES = {k: (effective_config({"kind": k}, period_s=1e-3)["mass_kg"],
               effective_config({"kind": k}, period_s=1e-3)["damping_n_s_per_m"]) for k in ("1dof", "planar", "spatial")}
#: the config's defaults the loop's rule runs with
K_CONTACT, B_CONTACT, K_COUPLING, B_COUPLING = 4000.0, 30.0, 1500.0, 15.0


def _rule(mass, kind, n_max=32, *, bd=0.0, k=K_CONTACT, b=B_CONTACT, kc=K_COUPLING, bc=B_COUPLING, g=1.0):
    md = DEVICES[kind][0]
    return sb.coupling_damping_for_tool(mass, device_mass_kg=md, device_damping_n_s_per_m=bd, contact_n_per_m=k,
                                        contact_n_s_per_m=b, max_contacts=n_max, coupling_n_per_m=kc,
                                        coupling_n_s_per_m=bc, env_gain=g)


def _worst_growth(mass, kind, b_c, n_max, *, bd=None, k=K_CONTACT, b=B_CONTACT, kc=K_COUPLING, g=1.0):
    """The largest growth rate over 1..n_max contacts (eigenvalues), the device's own damping
    unless ``bd`` says otherwise."""
    md, bd0 = DEVICES[kind]
    bd = bd0 if bd is None else bd
    return max(rest_growth_per_s(mass, md, bd, n * k, n * b, kc, b_c, g) for n in range(1, n_max + 1))


def test_the_defaults_bounce_and_the_rule_brings_the_2_kg_tools_to_rest():
    """The report: 2 kg on the planar device (two contacts) and 3 kg on the spatial one (four)
    grow at the configured 15 N s/m; with the rule's damping the loop decays on 1-32 contacts."""
    assert rest_growth_per_s(2.0, *DEVICES["planar"], 2 * K_CONTACT, 2 * B_CONTACT, K_COUPLING, B_COUPLING) > 1.0
    assert rest_growth_per_s(3.0, *DEVICES["spatial"], 4 * K_CONTACT, 4 * B_CONTACT, K_COUPLING, B_COUPLING) > 0.0
    for kind in DEVICES:
        for mass in (2.0, 3.0, 20.0):
            b = _rule(mass, kind)
            assert b > B_COUPLING
            assert _worst_growth(mass, kind, b, 32) < 0.0
    # the planar 2 kg tool: about 27.7 N s/m, its slowest mode decaying at more than 4 /s
    b = _rule(2.0, "planar")
    assert 26.0 < b < 29.0
    assert _worst_growth(2.0, "planar", b, 32) < -4.0


def test_light_tools_keep_the_configured_coupling():
    """Transparency: what a tool up to 0.79 kg renders does not change (the project's scenes' tools
    are 0.25 kg planar, 0.15 kg links, 1 kg on the 1dof peg)."""
    for kind in DEVICES:
        for mass in (0.005, 0.03, 0.1, 0.25, 0.5, 0.79):
            assert _rule(mass, kind) == B_COUPLING, (kind, mass)
    assert _rule(1.0, "1dof") == B_COUPLING


def test_the_margin_is_the_rules():
    """The damping set is HEAVY_TOOL_MARGIN times the least stable one: at the least one the
    loop is only just stable, a little below it unstable on some contact count."""
    for kind in ("planar", "spatial"):
        b = _rule(2.0, kind)
        least = b / sb.HEAVY_TOOL_MARGIN
        assert _worst_growth(2.0, kind, least * 1.001, 32, bd=0.0) < 0.0
        assert _worst_growth(2.0, kind, least * 0.99, 32, bd=0.0) > 0.0


def test_the_hurwitz_test_agrees_with_the_eigenvalues_across_the_bound():
    md, bd = DEVICES["planar"]
    for mass in (1.6, 1.65, 1.7, 1.75, 1.8, 2.0, 7.0, 7.5, 8.0):
        for n in (1, 2, 4, 32):
            stable = sb.rest_loop_stable(mass, device_mass_kg=md, device_damping_n_s_per_m=bd,
                                         contact_n_per_m=K_CONTACT, contact_n_s_per_m=B_CONTACT, max_contacts=n,
                                         coupling_n_per_m=K_COUPLING, coupling_n_s_per_m=B_COUPLING)
            worst = max(rest_growth_per_s(mass, md, bd, j * K_CONTACT, j * B_CONTACT, K_COUPLING, B_COUPLING)
                        for j in range(1, n + 1))
            assert stable == (worst < 0.0), (mass, n, worst)


def test_no_stated_handle_mass_keeps_the_configured_damping():
    kw = dict(device_damping_n_s_per_m=0.0, contact_n_per_m=K_CONTACT, contact_n_s_per_m=B_CONTACT, max_contacts=32,
              coupling_n_per_m=K_COUPLING, coupling_n_s_per_m=B_COUPLING)
    assert sb.coupling_damping_for_tool(2.0, device_mass_kg=None, **kw) == B_COUPLING
    assert sb.coupling_damping_for_tool(2.0, device_mass_kg=0.0, **kw) == B_COUPLING


def test_the_coupler_needs_nothing():
    for kind in DEVICES:
        for mass in (0.005, 2.0, 20.0, 1000.0):
            assert _rule(mass, kind, g=0.0) == B_COUPLING


KINDS = st.sampled_from(sorted(DEVICES))
MASSES = st.floats(math.log(0.005), math.log(20.0)).map(math.exp)


@settings(max_examples=150, deadline=None, derandomize=True, database=None)
@given(kind=KINDS, mass=MASSES, n_max=st.integers(1, 64), n_frac=st.floats(0.0, 1.0), more=st.floats(1.0, 20.0),
       device_damped=st.booleans())
def test_property_the_rules_damping_keeps_the_rest_loop_stable(kind, mass, n_max, n_frac, more, device_damped):
    """Any tool of 5 g - 20 kg, any capacity of 1-64 contacts, each simulated device, resting on
    any number of contacts up to the capacity: with the rule's damping (computed with no device
    damping assumed), and with any more damping, the eigenvalues' largest real part is negative,
    whether the handle's own damping is there or not."""
    n = 1 + int(n_frac * (n_max - 1))
    b = _rule(mass, kind, n_max)
    assert b is not None and b >= B_COUPLING
    bd = DEVICES[kind][1] if device_damped else 0.0
    md = DEVICES[kind][0]
    for bc in (b, b * more):
        assert rest_growth_per_s(mass, md, bd, n * K_CONTACT, n * B_CONTACT, K_COUPLING, bc) < 0.0, (bc, n)


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(kind=KINDS, mass=MASSES, k=st.floats(1e3, 1e5), tau=st.floats(1e-3, 2e-2), kc=st.floats(200.0, 5000.0),
       bc=st.floats(1.0, 60.0), g=st.floats(0.0, 1.0), n=st.integers(1, 32))
def test_property_other_contacts_and_couplings_too(kind, mass, k, tau, kc, bc, g, n):
    """The rule is the system's, not the defaults': any contact stiffness (damping as a time
    constant of it), coupling and force-channel gain."""
    b = sb.coupling_damping_for_tool(mass, device_mass_kg=DEVICES[kind][0], device_damping_n_s_per_m=0.0,
                                     contact_n_per_m=k, contact_n_s_per_m=tau * k, max_contacts=32,
                                     coupling_n_per_m=kc, coupling_n_s_per_m=bc, env_gain=g)
    assert b is not None and b >= bc
    assert rest_growth_per_s(mass, DEVICES[kind][0], 0.0, n * k, n * tau * k, kc, b, g) < 0.0


# ---------------------------------------------------------------------------- the controller
def _controller(kind="planar", rate=1000.0, **sections):
    data = {"loop": {"rate_hz": rate}, "device": {"driver": "sim", "kind": kind}}
    for key, v in sections.items():
        data.setdefault(key, {}).update(v)
    s = cfg.load(data)
    dev = make_sim_device({"kind": kind}, period_s=1.0 / rate, clock_ns=lambda: 0)
    c = ctl.Controller(s, kind, dev.limits)
    c.set_moving_figures(dev.info)
    return c


def test_the_controller_sets_the_damping_per_tool_and_back():
    c = _controller()
    assert c.cp[ctl.CP_BT] == B_COUPLING
    mass, b, why = c.fit_tool(ToolSpec.planar(2.0, 1e-3))
    assert (mass, why) == (2.0, "") and b == pytest.approx(_rule(2.0, "planar"))
    assert c.cp[ctl.CP_BT] == b
    # the stiffness and the rotational gains are not touched
    assert c.cp[ctl.CP_KT] == K_COUPLING and c.cp[ctl.CP_BR] == 0.015
    # the next session's light tool gets the configured damping back
    assert c.fit_tool(ToolSpec.planar(0.25, 1e-4))[1] == B_COUPLING and c.cp[ctl.CP_BT] == B_COUPLING
    # a linkage, or no tool, keeps it too
    chain = ToolSpec.linkage([LinkSpec(1.0, (0.03, 0, 0), (1e-4, 1e-4, 1e-4)),
                              LinkSpec(1.0, (0.03, 0, 0), (1e-4, 1e-4, 1e-4), 0, "revolute", (0.06, 0, 0))], held_link=0, planar=True)
    c.fit_tool(ToolSpec.planar(2.0, 1e-3))
    assert c.fit_tool(chain)[1] == B_COUPLING and c.cp[ctl.CP_BT] == B_COUPLING
    c.fit_tool(ToolSpec.planar(2.0, 1e-3))
    assert c.fit_tool(None)[1] == B_COUPLING


def test_the_controller_uses_the_configs_figures():
    # a heavier stated handle needs more (passivity.moving_mass_kg overrides the device's figure)
    light = _controller().fit_tool(ToolSpec.planar(2.0, 1e-3))[1]
    heavy = _controller(passivity={"moving_mass_kg": 1.0}).fit_tool(ToolSpec.planar(2.0, 1e-3))[1]
    assert heavy > light
    # more configured damping is kept as it is
    assert _controller(controller={"damping_n_s_per_m": 50.0}).fit_tool(ToolSpec.planar(2.0, 1e-3))[1] == 50.0
    # direct coupling has no coupling to damp
    c = _controller(controller={"type": "direct"})
    assert c.fit_tool(ToolSpec.planar(2.0, 1e-3))[1] == c.cp[ctl.CP_BT]


def test_a_tool_the_device_cannot_damp_enough_is_capped_and_named():
    """The damping the device renders bounds the rule (its moving mass x rate: 0.4 kg x 100 Hz =
    40 N s/m here); a 20 kg planar tool needs 41 N s/m: it gets the cap and the reason, naming the
    field (within a Reject's 120 characters)."""
    c = _controller(rate=100.0, safety={"allow_outside_stable_region": True})
    assert c._damping_cap == pytest.approx(40.0)
    assert _rule(20.0, "planar") > 40.0
    mass, b, why = c.fit_tool(ToolSpec.planar(20.0, 1e-2))
    assert why.startswith("tool.mass_kg: 20 kg needs more coupling damping than the device renders (40 N s/m)")
    assert b == pytest.approx(40.0) and c.cp[ctl.CP_BT] == b and len(why) <= 120
    assert c.fit_tool(ToolSpec.planar(2.0, 1e-3)) == (2.0, pytest.approx(_rule(2.0, "planar")), "")


def test_the_hello_refusal_names_the_field_and_the_largest_mass_that_works():
    c = _controller(rate=100.0, safety={"allow_outside_stable_region": True})
    why = c.hello_refusal(ToolSpec.planar(20.0, 1e-2))
    assert why.startswith("tool.mass_kg: 20 kg needs 41.1 N s/m of coupling damping to rest, the device renders 40;")
    assert len(why) <= 120, why
    most = float(why.rsplit("at most ", 1)[1].split(" kg")[0])
    # the largest that works: just below it the rule's damping is within the cap, just above not
    assert _rule(most * 0.999, "planar") <= 40.0 < _rule(most * 1.01, "planar")
    assert 2.0 < most < 20.0
    assert c.hello_refusal(ToolSpec.planar(most * 0.99, 1e-2)) == ""
    assert c.hello_refusal(ToolSpec.planar(2.0, 1e-3)) == ""
    # at 1 kHz the device renders 400 N s/m: nothing is refused
    assert _controller().hello_refusal(ToolSpec.planar(20.0, 1e-2)) == ""
    assert _controller().hello_refusal(ToolSpec.planar(1000.0, 1.0)) == ""


def test_the_rule_is_cheap_enough_for_an_engagement():
    """Counted, not timed: the bisection's Hurwitz checks per tool (each a few array operations
    over the contact counts), and a second engagement of the same mass reuses the first's."""
    calls = []
    real = sb.rest_loop_stable

    def counting(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    sb.rest_loop_stable = counting
    try:
        c = _controller()
        c.fit_tool(ToolSpec.planar(2.0, 1e-3))
        first = len(calls)
        c.fit_tool(ToolSpec.planar(2.0, 1e-3))
    finally:
        sb.rest_loop_stable = real
    assert first <= 50 and len(calls) == first   # the translation's search and the turn's, about 20 each
    assert np.isfinite(c.cp[ctl.CP_BT])


# ---------------------------------------------------------------------------- the turn
#: the simulated handles' moments (kg m^2): planar I_zz; spatial the largest principal one
HANDLE_MOMENTS = {"planar": 1e-3, "spatial": 6e-4}
KR, BR, TAU = 1.5, 0.015, B_CONTACT / K_CONTACT


def _rot_rule(moment, kind, *, bd=0.0):
    return sb.rot_coupling_damping_for_tool([moment], device_inertia_kg_m2=HANDLE_MOMENTS[kind],
                                            device_rot_damping_n_m_s_per_rad=bd, contact_damping_per_stiffness_s=TAU,
                                            coupling_n_m_per_rad=KR, coupling_n_m_s_per_rad=BR)


def test_the_turn_of_a_heavy_tool_bounced_and_the_rule_steadies_it():
    """The same loop about a turn: a 2 kg rod of 150 mm (3.75e-3 kg m^2) on the planar handle
    (1e-3 kg m^2, 2e-3 N m s/rad) grows on its two corners (lever 20 mm) with the configured
    0.015 N m s/rad; with the rule's 0.060 it decays, on any contact stiffness."""
    k_two = 2 * K_CONTACT * 0.02 ** 2
    assert rest_growth_per_s(3.75e-3, 1e-3, 2e-3, k_two, TAU * k_two, KR, BR) > 1.0
    b = _rot_rule(3.75e-3, "planar")
    assert 0.055 < b < 0.065
    for scale in np.geomspace(1e-3, 1e6, 200):
        k = KR * scale
        assert rest_growth_per_s(3.75e-3, 1e-3, 2e-3, k, TAU * k, KR, b) < 0.0, scale


def test_a_moment_below_the_handles_keeps_the_configured_rotational_damping():
    for kind, i_d in HANDLE_MOMENTS.items():
        for moment in (1e-7, 1e-5, 1.417e-4, 0.99 * i_d):
            assert _rot_rule(moment, kind) == BR, (kind, moment)
    assert sb.rot_coupling_damping_for_tool([1.0], device_inertia_kg_m2=None, device_rot_damping_n_m_s_per_rad=0.0,
                                            contact_damping_per_stiffness_s=TAU, coupling_n_m_per_rad=KR,
                                            coupling_n_m_s_per_rad=BR) == BR


@settings(max_examples=80, deadline=None, derandomize=True, database=None)
@given(kind=st.sampled_from(sorted(HANDLE_MOMENTS)), moment=st.floats(math.log(1e-7), math.log(10.0)).map(math.exp),
       scale=st.floats(math.log(1e-3), math.log(1e6)).map(math.exp), more=st.floats(1.0, 20.0),
       damped=st.booleans())
def test_property_the_rotational_rule_keeps_the_turn_at_rest_stable(kind, moment, scale, more, damped):
    """Any moment 1e-7 - 10 kg m^2 on each simulated handle, any rotational contact stiffness
    (1e-3 to 1e6 x the coupling's spring, damping the contacts' 7.5 ms of it): the rule's damping and
    more keep the eigenvalues' largest real part negative, the handle damped or not."""
    b = _rot_rule(moment, kind)
    assert b is not None and b >= BR
    bd = {"planar": 2e-3, "spatial": 1e-3}[kind] if damped else 0.0
    k = KR * scale
    for br in (b, b * more):
        assert rest_growth_per_s(moment, HANDLE_MOMENTS[kind], bd, k, TAU * k, KR, br) < 0.0


def test_the_controller_sets_the_rotational_damping_per_tool():
    c = _controller()
    c.fit_tool(ToolSpec.planar(2.0, 3.75e-3))
    assert c.cp[ctl.CP_BR] == pytest.approx(_rot_rule(3.75e-3, "planar")) and c.fit_rot[1] == ""
    assert c._rot_damping_cap == pytest.approx(1.0)           # the handle's 1e-3 kg m^2 x 1 kHz
    c.fit_tool(ToolSpec.planar(2.0, 1e-7))
    assert c.cp[ctl.CP_BR] == BR
    # a spatial tool: its largest need over its principal moments, on the handle's largest moment
    c = _controller("spatial")
    assert c._heavy_rot["device_inertia_kg_m2"] == pytest.approx(6e-4)
    c.fit_tool(ToolSpec.spatial(2.0, (1e-5, 2e-3, 1e-5)))
    assert c.cp[ctl.CP_BR] == pytest.approx(_rot_rule(2e-3, "spatial"))
    # a 1dof tool has no turn
    c = _controller("1dof")
    c.fit_tool(ToolSpec.one_dof(2.0))
    assert c.cp[ctl.CP_BR] == BR


def test_the_handshake_refuses_a_tool_the_device_cannot_bring_to_rest():
    """Through the server's handshake (100 Hz, where the planar device renders at most 40 N s/m of
    coupling damping): a 20 kg planar tool is refused by name with the largest mass that works;
    a 2 kg one is welcome."""
    from server_harness import make_settings

    from hapticproxy.protocol.messages import ErrorCode, Hello, ToolKind
    from hapticproxy.protocol.session import ClientEndpoint
    from hapticproxy.protocol.transport import open_transport
    from hapticproxy.server.clock import SimClock
    from hapticproxy.server.loop import HapticLoop

    s = make_settings(loop={"rate_hz": 100.0}, safety={"allow_outside_stable_region": True})
    clock = SimClock(start_ns=1_000_000_000)
    loop = HapticLoop.build(s, clock=clock)
    tr = open_transport(s["transport"]["url"], "client")
    try:
        loop.start()
        out = {}
        for nonce, mass in ((1, 20.0), (2, 2.0)):
            ep = ClientEndpoint(tr.send, Hello(client_nonce=nonce, tool_kind=ToolKind.PLANAR, mass_kg=mass,
                                               inertia_kg_m2=(1e-2, 1e-2, 1e-2, 0.0, 0.0, 0.0), max_contacts=8))
            ep.start(clock.now_ns())
            for _ in range(50):
                loop.step()
                while (item := tr.recv()) is not None:
                    ep.receive(item[0], item[1], clock.now_ns())
                if ep.reject is not None or ep.established:
                    break
            out[mass] = ep
        assert out[20.0].reject is not None and out[20.0].reject.code == ErrorCode.INVALID_HELLO
        assert out[20.0].reject.reason.startswith("tool.mass_kg: 20 kg needs 41.1 N s/m of coupling damping"), \
            out[20.0].reject.reason
        assert "at most" in out[20.0].reject.reason
        assert out[2.0].reject is None and out[2.0].established
    finally:
        tr.close()
        loop.close()
