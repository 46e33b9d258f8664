"""The stable-region bound (server/stability.py) against the measured table, and the config
refusing what lies outside it (issue 13 section 5)."""
import json
import logging
from pathlib import Path

import pytest

from hapticproxy.server import config as cfg
from hapticproxy.server import stability as st

ROOT = Path(__file__).resolve().parents[2]
REGION = json.loads((ROOT / "docs" / "experiments" / "tradeoff.json").read_text())["stable_region"]
#: the same grid re-measured with the server's current defaults (issue 31: the implicit step, the layer)
REMEASURED = json.loads((ROOT / "docs" / "experiments" / "stable_region.json").read_text())
#: the sweep's row -> the config that row was measured with (experiments/tradeoff.py REGION_CONTROLLERS)
ROW_CONFIG = {
    "four_channel": dict(controller={"type": "four_channel"}, model={"policy": "deformation"}),
    "coupler": dict(controller={"type": "coupler"}, model={"policy": "deformation"}),
    "direct": dict(controller={"type": "direct"}, model={"policy": "deformation"}),
    "IR (direct, rigid, eps 0, eq. 1)": dict(controller={"type": "direct"},
                                             model={"policy": "rigid", "epsilon_m": 0.0, "contact_frame": "proxy"}),
    "four_channel, b = 30 N s/m": dict(controller={"type": "four_channel"}, model={"policy": "deformation"}),
}


def _settings(row: str, rate: float, k: float, **safety):
    c = ROW_CONFIG[row]
    b = 30.0 if row == st.FIXED_DAMPING_ROW else st.DAMPING_PER_STIFFNESS_S * k
    return cfg.load({"loop": {"rate_hz": rate}, "controller": dict(c["controller"]),
                     "model": {**c["model"], "stiffness_n_per_m": k, "damping_n_s_per_m": b},
                     "safety": safety})


def test_the_table_is_the_measured_one():
    rows = {}
    for r in REGION:
        rows.setdefault(r["controller"], {})[r["rate_hz"]] = r["largest_stable_stiffness_n_per_m"]
    for name, ks in st.MEASURED.items():
        assert tuple(rows[name][rate] for rate in st.RATES_HZ) == ks, name
    assert tuple(rows[st.FIXED_DAMPING_ROW][rate] for rate in st.RATES_HZ) == st.MEASURED_FIXED_DAMPING
    assert set(rows) == set(st.MEASURED) | {st.FIXED_DAMPING_ROW}


def test_the_bound_lies_inside_the_region_re_measured_with_the_current_defaults():
    new = {(r["controller"], r["rate_hz"]): r for r in REMEASURED["stable_region"]}
    bound = dict(st.MEASURED, **{st.FIXED_DAMPING_ROW: st.MEASURED_FIXED_DAMPING})
    assert set(new) == {(row, rate) for row in bound for rate in st.RATES_HZ}   # every cell re-measured
    for row, ks in bound.items():
        for rate, k in zip(st.RATES_HZ, ks):
            e = new[(row, rate)]
            # every stiffness from the band's lower end up to the bound was stable in the re-measurement
            assert e["smallest_stable_stiffness_n_per_m"] is not None, (row, rate)
            assert e["largest_stable_stiffness_n_per_m"] >= k, (row, rate, k)
            inside = [t for t in e["tried"] if e["smallest_stable_stiffness_n_per_m"] <= t["stiffness_n_per_m"] <= k]
            assert inside and not any(t["unstable"] or t["refused"] for t in inside), (row, rate, k)
    # measured with what the server runs by default
    s = REMEASURED["settings"]
    assert s["passivity_enabled"] == cfg.load({})["passivity"]["enabled"] and s["layer"] == "default"
    from hapticproxy.server.model.model import LocalModel, ToolSpec
    assert s["integrator"] == LocalModel(ToolSpec.planar(0.25, 1e-3), warm=False).integrator
    assert not REMEASURED["quick"]


@pytest.mark.parametrize("row", sorted(st.MEASURED))
def test_the_rule_gives_each_rows_largest_stable_stiffness_at_the_measured_rates(row):
    controller, policy = (("direct", "rigid") if row == st.IR_ROW else (row, "deformation"))
    for rate, k in zip(st.RATES_HZ, st.MEASURED[row]):
        lim = st.stable_contact_limits(rate, controller, policy)
        assert lim == (k, 0.0075)
        k_max, b_rule = lim                                   # what the handshake unpacks
        assert k_max == k and b_rule * k_max == lim.b_max_n_s_per_m


@pytest.mark.parametrize("row", sorted(ROW_CONFIG))
def test_every_measured_point_is_accepted_if_stable_and_refused_if_unstable_above_the_band(row):
    for r in (r for r in REGION if r["controller"] == row):
        top = r["largest_stable_stiffness_n_per_m"]
        for t in r["tried"]:
            k = t["stiffness_n_per_m"]
            if not t["unstable"] and k <= top:
                s = _settings(row, r["rate_hz"], k)
                assert s.outside_stable_region == ()
            elif k > top:
                with pytest.raises(cfg.ConfigError) as e:
                    _settings(row, r["rate_hz"], k)
                assert e.value.key == "model.stiffness_n_per_m", (row, r["rate_hz"], k)
                assert f"nearest safe value {top:g}" in e.value.reason
                assert "allow_outside_stable_region" in e.value.reason


def test_between_and_beyond_the_measured_rates_the_rule_is_conservative():
    for row in ("four_channel", "direct"):
        ks = st.MEASURED[row]
        for i in range(len(st.RATES_HZ) - 1):
            lo, hi = st.RATES_HZ[i], st.RATES_HZ[i + 1]
            for rate in (lo + 1.0, 0.5 * (lo + hi), hi - 1.0):
                assert st.stable_contact_limits(rate, row).k_max_n_per_m == min(ks[i], ks[i + 1])
        # below the sweep: the explicit step's limit scales with rate^2; above: never extrapolated
        assert st.stable_contact_limits(128.0, row).k_max_n_per_m == pytest.approx(ks[0] / 4)
        assert st.stable_contact_limits(100.0, row).k_max_n_per_m < ks[0]
        assert st.stable_contact_limits(20000.0, row).k_max_n_per_m == ks[-1]
    # the IR's band falls from 512 Hz to 1 kHz: between them the smaller one holds
    assert st.stable_contact_limits(700.0, "direct", "rigid").k_max_n_per_m == 10000.0
    # policies without proxy deformation take the IR row where it is lower
    assert st.stable_contact_limits(4000.0, "four_channel", "lm0").k_max_n_per_m == 10000.0
    assert st.stable_contact_limits(4000.0, "four_channel", "deformation").k_max_n_per_m == 200000.0
    with pytest.raises(ValueError, match="controller"):
        st.stable_contact_limits(1000.0, "pid")


def test_the_issues_settings_are_refused_with_the_reason_and_the_nearest_safe_value():
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load({"model": {"stiffness_n_per_m": 1e6}})
    assert e.value.key == "model.stiffness_n_per_m"
    assert "1e+06 N/m is outside the stable region" in e.value.reason and "1000 Hz" in e.value.reason
    assert "nearest safe value 50000" in e.value.reason
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load({"safety": {"force_rate_n_per_s": 1e6}})
    assert e.value.key == "safety.force_rate_n_per_s" and "nearest safe value 1000" in e.value.reason
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load({"model": {"damping_n_s_per_m": 1000.0}})
    assert e.value.key == "model.damping_n_s_per_m" and "nearest safe value 375" in e.value.reason
    # b <= 30 N s/m: the four-channel controller's fixed-damping sweep is stable to 1 MN/m at 4 kHz
    assert cfg.load({"preset": "accurate", "model": {"stiffness_n_per_m": 1e6, "damping_n_s_per_m": 30.0}})
    with pytest.raises(cfg.ConfigError, match="model.stiffness_n_per_m"):
        cfg.load({"preset": "accurate", "model": {"stiffness_n_per_m": 1e6, "damping_n_s_per_m": 31.0}})


@pytest.mark.parametrize("rate", [256.0, 512.0, 1000.0, 4000.0, 20000.0])
def test_one_step_changes_the_force_by_at_most_1_n(rate):
    s = cfg.load({"loop": {"rate_hz": rate}, "model": {"stiffness_n_per_m": 1000.0, "damping_n_s_per_m": 1.0}})
    per_step = s["safety"]["force_rate_n_per_s"] / rate
    assert per_step <= st.MAX_FORCE_STEP_N
    assert s["safety"]["force_rate_n_per_s"] == min(1000.0, rate)     # auto: the old 1 kN/s where it fits
    cfg.load({"loop": {"rate_hz": rate}, "model": {"stiffness_n_per_m": 1000.0, "damping_n_s_per_m": 1.0},
              "safety": {"force_rate_n_per_s": rate}})
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load({"loop": {"rate_hz": rate}, "model": {"stiffness_n_per_m": 1000.0, "damping_n_s_per_m": 1.0},
                  "safety": {"force_rate_n_per_s": rate * 1.01}})
    assert e.value.key == "safety.force_rate_n_per_s" and f"nearest safe value {rate:g}" in e.value.reason


def test_the_override_accepts_and_says_so(caplog):
    from hapticproxy.server.daemon import warn_outside_stable_region
    from hapticproxy.server.status import format_status

    s = cfg.load({"model": {"stiffness_n_per_m": 1e6}, "safety": {"force_rate_n_per_s": 1e6,
                                                                   "allow_outside_stable_region": True}})
    assert [k for k, _ in s.outside_stable_region] == ["model.stiffness_n_per_m", "safety.force_rate_n_per_s"]
    assert s["model"]["stiffness_n_per_m"] == 1e6
    with caplog.at_level(logging.WARNING, logger="hapticproxy.serve"):
        warn_outside_stable_region(s)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2 and "OUTSIDE THE STABLE REGION" in warnings[0].getMessage()
    text = format_status({"outside_stable_region": [f"{k}: {w}" for k, w in s.outside_stable_region]})
    assert text.count("WARNING") == 2 and "model.stiffness_n_per_m" in text
    assert "WARNING" not in format_status({"outside_stable_region": []})
    assert cfg.load().outside_stable_region == ()


def test_a_spring_stiffer_than_the_devices_mass_takes_is_refused():
    from hapticproxy.server.devices import sim

    assert st.DEVICE_SPRING_STABILITY == sim.ENDSTOP_STABILITY
    # a 10 g 1-DOF handle at 256 Hz takes 2 x 0.01 x 256^2 = 1311 N/m: the 1500 N/m coupling is too stiff
    dev = {"kind": "1dof", "mass_kg": 0.01}
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load({"loop": {"rate_hz": 256.0}, "device": dev})
    assert e.value.key == "controller.stiffness_n_per_m" and "nearest safe value 1310.72" in e.value.reason
    cfg.load({"loop": {"rate_hz": 256.0}, "device": dev, "controller": {"stiffness_n_per_m": 1310.0}})
    # direct coupling: the device is the tool, the contact spring acts on its mass
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load({"loop": {"rate_hz": 256.0}, "device": dev, "controller": {"type": "direct"},
                  "model": {"stiffness_n_per_m": 2000.0, "damping_n_s_per_m": 10.0}})
    assert e.value.key == "model.stiffness_n_per_m" and "device's 0.01 kg" in e.value.reason
    s = cfg.load({"loop": {"rate_hz": 256.0}, "device": dev, "safety": {"allow_outside_stable_region": True}})
    assert [k for k, _ in s.outside_stable_region] == ["controller.stiffness_n_per_m"]
