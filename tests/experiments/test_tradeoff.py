"""The speed / accuracy trade-off, short version (simulated time; the real-time achieved-rate runs
and the full sweep are opt-in: ``hapticproxy experiment tradeoff`` and the ``slow`` test)."""
from __future__ import annotations

import json

import pytest

from hapticproxy.experiments import tradeoff as T

ROW_KEYS = {"dimension", "label", "rate_hz", "stiffness_n_per_m", "epsilon_m", "capacity", "env_rate_hz", "kernel",
            "wall_error_mm", "limit_cycle_mm", "drift_mm", "rotation_deg", "force_step_max_n", "penalty_jump_max_n",
            "energy_injected_mj", "unstable", "step_us_p50", "step_us_p99", "model_us_p50", "numpy_model_us_p50",
            "cpu_load_pct", "feasible"}


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("tradeoff")
    return out, T.run_tradeoff(out, quick=True, realtime=False)


def test_quick_tradeoff_writes_its_table_plots_and_rows(quick):
    out, res = quick
    for name in ("tradeoff.json", "tradeoff.md", "stable_region.md", "pareto.png", "stable_region.png"):
        assert (out / name).stat().st_size > 100, name
    saved = json.loads((out / "tradeoff.json").read_text())
    assert len(saved["rows"]) == len(res["rows"]) >= 8
    dims = {r["dimension"] for r in res["rows"]}
    assert {"haptic rate", "epsilon", "stiffness", "kernel", "recovery", "advice"} <= dims
    for r in res["rows"]:
        assert ROW_KEYS <= set(r), sorted(ROW_KEYS - set(r))
    assert "| dimension | label |" in (out / "tradeoff.md").read_text()


def test_epsilon_buys_wall_accuracy_and_rate_buys_smaller_force_steps(quick):
    _, res = quick
    rows = res["rows"]
    eps = {r["epsilon_m"]: r for r in rows if r["dimension"] == "epsilon"}
    # with the deformation recovery both end at the wall; epsilon gets there sooner (no deformation)
    assert eps[0.005]["surface_reached_s"] < eps[0.0]["surface_reached_s"]
    assert eps[0.005]["wall_error_mm"] <= eps[0.0]["wall_error_mm"]
    rec = {r["recovery_speed_m_per_s"]: r for r in rows if r["dimension"] == "recovery"}
    assert rec[None]["wall_error_mm"] < min(0.1, rec[0.0]["wall_error_mm"])     # recovery buys the wall
    assert rec[0.0]["recovery_energy_mj"] == 0.0 < rec[None]["recovery_energy_mj"]
    adv = next(r for r in rows if r["dimension"] == "advice")
    assert adv["advice"] == "epsilon+lead" and adv["wall_error_mm"] < 0.1 and not adv["unstable"]
    rate = {r["rate_hz"]: r for r in rows if r["dimension"] == "haptic rate"}
    assert rate[2000.0]["force_step_max_n"] < rate[512.0]["force_step_max_n"]
    assert rate[2000.0]["cpu_load_pct"] > rate[512.0]["cpu_load_pct"]         # and costs more CPU
    assert not any(r["unstable"] for r in rate.values())


def test_numpy_kernel_costs_more_for_the_same_step(quick):
    _, res = quick
    kern = [r for r in res["rows"] if r["dimension"] == "kernel"]
    by = {(r["rate_hz"], r["kernel"]): r for r in kern}
    for rate in (512.0, 2000.0):
        nb, npy = by[(rate, "numba")], by[(rate, "numpy")]
        assert npy["step_us_p50"] > 2 * nb["step_us_p50"]                      # a ratio, not a time
        assert npy["wall_error_mm"] == nb["wall_error_mm"] and npy.get("cost_projected")
    check = res["numpy_matches_numba"]
    assert check["peg1d_max_position_difference_m"] <= 1e-9
    assert check["planar_step_max_q_difference"] <= 1e-9
    assert check["planar_step_max_wrench_difference"] <= 1e-6


def test_stable_region_has_a_band_per_controller_and_rate(quick):
    _, res = quick
    region = res["stable_region"]
    assert {e["controller"] for e in region} == {name for name, _ in T.REGION_CONTROLLERS}
    assert {e["rate_hz"] for e in region} == set(T.QUICK_REGION_RATES)
    for e in region:
        assert e["tried"] and all("unstable" in t for t in e["tried"])


def test_pareto_front_keeps_only_undominated_stable_rows():
    rows = [
        {"label": "a", "cpu_load_pct": 1.0, "err": 5.0, "unstable": False},
        {"label": "b", "cpu_load_pct": 2.0, "err": 3.0, "unstable": False},
        {"label": "c", "cpu_load_pct": 3.0, "err": 4.0, "unstable": False},   # dominated by b
        {"label": "d", "cpu_load_pct": 0.5, "err": 0.1, "unstable": True},    # unstable: never on it
        {"label": "e", "cpu_load_pct": 4.0, "err": 1.0, "unstable": False},
    ]
    assert [r["label"] for r in T.pareto_front(rows, "cpu_load_pct", "err")] == ["a", "b", "e"]


@pytest.mark.slow
def test_full_tradeoff(tmp_path):
    res = T.run_tradeoff(tmp_path, quick=False, realtime=True)
    assert len(res["rows"]) > 40
    assert all("error" not in r for r in res["realtime_rates"])
