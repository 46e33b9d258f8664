"""The surface is felt where it is (issue 15), on the whole server loop in simulated time: the
deformation recovery, the predicted epsilon and the lead, each against the paper's model."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hapticproxy.experiments import fidelity as FD
from hapticproxy.experiments import metrics as M
from hapticproxy.experiments.harness import run_simulated


def _wall(method, config, push, lag, seed):
    tr = run_simulated(FD.wall_spec(method, config, push, lag, seed))
    return tr, M.felt_surface_metrics(tr, surface_m=M.WALL_Y_MM / 1e3, axis=1, push_n=push), M.static_contact_metrics(tr)


def test_recovery_puts_a_late_wall_where_it_is_within_two_seconds():
    # 0.5 N, the engine's tool 30 ms behind, seed 2: the first contact reaches the model 16.6 mm
    # beyond the wall (the device is written first in each step and the update applied after it,
    # so a scenario's timing differs by a step from the tree this test was written on, where the
    # same seed without the lag did it)
    _, paper, _ = _wall("LM5", "paper", 0.5, 0.03, 2)
    tr, rec, st = _wall("LM5", "recovery", 0.5, 0.03, 2)
    assert paper["surface_error_mm"] > 10.0
    assert abs(rec["surface_error_mm"]) < M.SURFACE_BAND_MM
    assert float(rec["surface_reached_s"]) < 2.0
    assert st["settled"]
    # the force the recovery adds changes at most at its bound (200 N/s: 0.39 N per 512 Hz step)
    assert 0.99 * 200.0 / 512.0 < rec["recovery_force_step_max_n"] <= 200.0 / 512.0 + 1e-9
    # the energy it gave: about the push times the distance it moved the device out, no more
    moved_mm = paper["surface_error_mm"]
    assert 0.5 * 0.5 * moved_mm < rec["recovery_energy_mj"] < 1.5 * 0.5 * moved_mm
    assert np.max(tr.env[:, 1]) <= 1e-9                   # the wall never pulls


def test_predicted_epsilon_catches_a_fast_approach_and_does_not_inflate_a_slow_one():
    # 1 N (0.8 m/s) with the engine's tool 20 ms behind: 10 mm beyond the wall with epsilon 5 mm
    tr_p, paper, _ = _wall("LM5", "paper", 1.0, 0.02, 1)
    tr, pred, st = _wall("LM5", "predicted", 1.0, 0.02, 1)
    assert paper["surface_error_mm"] > 5.0
    assert abs(pred["surface_error_mm"]) < M.SURFACE_BAND_MM
    assert st["first_contact_mm"] < M.WALL_Y_MM                # in the model before the proxy got there
    assert pred["recovery_energy_mj"] == 0.0                   # no recovery: nothing to recover
    eps_fast = tr.extra["advice"]["epsilon_mm"][1]
    assert FD.PREDICTED_CAP_M * 1e3 / 4 < eps_fast <= FD.PREDICTED_CAP_M * 1e3
    slow, _, _ = _wall("LM5", "predicted", 0.1, 0.0, 1)
    assert slow.extra["advice"]["epsilon_mm"][1] < eps_fast / 3


def test_the_lead_keeps_a_lagging_engine_on_the_proxy():
    # 1 N, the engine's tool 80 ms behind, no recovery, every seed of the experiment: the
    # predicted epsilon alone (capped at 40 mm) misses the wall in each run; with the lead the
    # engine's tool is on the proxy and each run feels the wall where it is. (At 40 ms the
    # predicted epsilon alone misses in one seed of five, 3, and that miss hangs on the timing of
    # a single step: a claim about the lead needs a lag it cannot cover alone in any run.)
    for seed in FD.SEEDS:
        spec = FD.wall_spec("LM5", "predicted", 1.0, 0.08, seed)
        tr0 = run_simulated(spec)
        tr1 = run_simulated(spec.but(lead=True))
        e0 = M.felt_surface_metrics(tr0, surface_m=M.WALL_Y_MM / 1e3, axis=1, push_n=1.0)["surface_error_mm"]
        e1 = M.felt_surface_metrics(tr1, surface_m=M.WALL_Y_MM / 1e3, axis=1, push_n=1.0)["surface_error_mm"]
        assert e0 > 5.0 and abs(e1) < M.SURFACE_BAND_MM, (seed, e0, e1)
        assert tr0.extra["advice"]["lead_ms"] == 0.0
        adv = tr1.extra["advice"]
        assert 30.0 < adv["lead_ms"] <= 100.0 and adv["lag_samples"] > 5, (seed, adv)
        assert M.static_contact_metrics(tr1)["first_contact_mm"] < M.WALL_Y_MM - 5.0, seed


def test_quick_fidelity_writes_its_tables(tmp_path):
    res = FD.run_fidelity(tmp_path, quick=True)
    saved = json.loads((tmp_path / "fidelity.json").read_text())
    assert len(saved["wall"]) == len(res["wall"]) == 2 * 2 + 2 * 4      # LM0: 2 configs, LM5: 4; 2 lags
    assert "| method | config |" in (tmp_path / "fidelity.md").read_text()
    after = [r for r in res["wall"] if r["config"] in ("recovery", "all")]
    assert all(r["within_0_5_mm"] == len(res["seeds"]) for r in after)
    paper = [r for r in res["wall"] if r["config"] == "paper"]
    assert all(r["within_0_5_mm"] < len(res["seeds"]) for r in paper)
    assert all(r["force_step_max_n"] <= 1000.0 / 512.0 + 1e-6 for r in res["wall"])   # the rate limit
    peg = {(r["method"], r["config"]): r for r in res["peg"]}
    assert not any(r["unstable"] for r in res["peg"])
    # the peg without epsilon (active geometry, 20 ms behind): the recovery pushes the hand back
    # to the hole's centre update after update, about 20 mJ/s given to the hand. With the
    # passivity layer (the default) it slows and stops while the tank is low (10 mJ spent in the
    # first 1.3 s), the peg leaves the centre and swings between the walls (EXPERIMENTS.md,
    # transparency): the recovery still narrows the error; without the layer it halves it
    assert peg[("LM0", "recovery")]["peg_error_mm"] < peg[("LM0", "paper")]["peg_error_mm"]
    bare = FD.peg_rows(lags=(0.0,), quick=True, passivity=(("enabled", False),))
    bare = {(r["method"], r["config"]): r for r in bare}
    assert bare[("LM0", "recovery")]["peg_error_mm"] < 0.5 * bare[("LM0", "paper")]["peg_error_mm"]
    assert bare[("LM0", "recovery")]["peg_error_mm"] < 0.5 * peg[("LM0", "recovery")]["peg_error_mm"]


@pytest.mark.slow
def test_spatial_box_on_a_floor_is_felt_where_it_is(tmp_path):
    pytest.importorskip("pybullet")
    spec = FD.spatial_spec("floor", "paper", 0.02, 1.0)
    tr0 = run_simulated(spec)
    tr1 = run_simulated(FD.spatial_spec("floor", "all", 0.02, 1.0))
    e = []
    for tr in (tr0, tr1):
        push = float(np.mean(np.abs(tr.cmd_xyz[tr.t_s >= tr.t_s[-1] - 1.0, 2])))
        assert push == pytest.approx(0.5, abs=0.02)
        e.append(M.felt_surface_metrics(tr, surface_m=FD.FLOOR_Z_M, axis=2, push_n=push, sign=-1.0))
    assert e[0]["surface_error_mm"] > 5.0                  # the paper's model: felt 5+ mm too deep
    assert abs(e[1]["surface_error_mm"]) < M.SURFACE_BAND_MM and float(e[1]["surface_reached_s"]) < 2.0
    assert tr1.faults == 0
