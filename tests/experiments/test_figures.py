"""The paper's experiments, reproduced (simulated time: deterministic, a second or two each), the
metric definitions on hand-made traces, and the ``hapticproxy experiment`` command."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hapticproxy.experiments import figures as F
from hapticproxy.experiments import metrics as M
from hapticproxy.experiments.cli import main as experiment_main
from hapticproxy.experiments.harness import Hand, RunSpec, Trace


def _trace(t, dev, *, cmd=None, vel=None, contacts=None, hand_start=0.0, spec=None, faults=0):
    n = len(t)
    return Trace(spec=spec or RunSpec(), mode="simulated", t_s=np.asarray(t, float), hand_start_s=hand_start,
                 dev=np.asarray(dev, float), proxy=np.asarray(dev, float),
                 dev_vel=np.zeros((n, 3)) if vel is None else np.asarray(vel, float),
                 cmd=np.zeros((n, 3)) if cmd is None else np.asarray(cmd, float), env=np.zeros((n, 3)),
                 contacts=np.ones(n) if contacts is None else np.asarray(contacts, float), updates=np.arange(n) + 1.0,
                 state=np.ones(n), rate_hz=1000.0, achieved_rate_hz=1000.0, env_rate_hz=50.0, faults=faults,
                 model_nonfinite=0, rate_limited=0, saturated=0)


# ------------------------------------------------------------------------------ metric definitions
def test_static_contact_metrics_of_a_device_at_rest_and_of_a_limit_cycle():
    t = np.arange(0, 5.0, 1e-3)
    y = np.where(t < 1.0, 0.124 * t, 0.1245)                       # reaches the wall, rests 0.5 mm beyond
    rest = M.static_contact_metrics(_trace(t, np.column_stack([0 * t, y, 0 * t]), contacts=(t >= 0.99)))
    assert rest["felt_wall_mm"] == pytest.approx(124.5, abs=1e-6)
    assert rest["wall_error_mm"] == pytest.approx(0.5, abs=1e-6)
    assert rest["limit_cycle_amplitude_mm"] == 0.0 and rest["settled"]
    assert rest["first_contact_mm"] == pytest.approx(124 * 0.99, abs=0.01)   # the first step with a contact
    # a 3 mm, 1 deg rotational limit cycle about 120 mm
    yc = 0.120 + 0.003 * np.sin(2 * np.pi * 4 * t)
    th = np.radians(1.0) * np.sin(2 * np.pi * 4 * t)
    cyc = M.static_contact_metrics(_trace(t, np.column_stack([0 * t, yc, th])))
    assert cyc["limit_cycle_amplitude_mm"] == pytest.approx(3.0, rel=1e-3)
    assert cyc["limit_cycle_rotation_deg"] == pytest.approx(1.0, rel=1e-3)
    assert not cyc["settled"]
    assert cyc["felt_wall_mm"] == pytest.approx(120.0, abs=0.01)


def test_injected_energy_is_the_work_of_the_command_on_the_device():
    t = np.arange(0, 4.0, 1e-3)
    v = np.column_stack([np.full_like(t, 0.1), 0 * t, 0 * t])
    push = _trace(t, 0 * v, cmd=np.column_stack([np.full_like(t, 2.0), 0 * t, 0 * t]), vel=v)
    assert M.injected_energy_mj(push) == pytest.approx(2.0 * 0.1 * 2.0 * 1e3, rel=1e-3)   # 2 N x 0.1 m/s x 2 s
    brake = _trace(t, 0 * v, cmd=np.column_stack([np.full_like(t, -2.0), 0 * t, 0 * t]), vel=v)
    assert M.injected_energy_mj(brake) < 0


def test_hole_metrics_flag_an_active_interaction_and_a_run_away_not_a_drift():
    spec = RunSpec(scene="hole", hand=Hand("sinusoid", (1.0, 0.0, 0.0), 2.5, 0.0))
    t = np.arange(0, 4.0, 1e-3)
    x = 0.005 * np.sin(2 * np.pi * 2.5 * t)                          # 10 mm of travel: drift, bounded
    vx = 0.005 * 2 * np.pi * 2.5 * np.cos(2 * np.pi * 2.5 * t)
    dev = np.column_stack([x, np.full_like(t, M.HOLE_Y_MM / 1e3), np.full_like(t, math.pi / 2)])
    vel = np.column_stack([vx, 0 * t, 0 * t])
    passive = M.hole_metrics(_trace(t, dev, vel=vel, cmd=-5.0 * vel, spec=spec))   # a damper: absorbs
    assert passive["x_travel_mm"] == pytest.approx(10.0, rel=1e-3)
    assert passive["drift_mm"] == pytest.approx(5.0, rel=1e-3)
    assert passive["rotation_deg"] == pytest.approx(0.0, abs=1e-9)
    assert passive["energy_injected_mj"] < 0 and not passive["unstable"]
    active = M.hole_metrics(_trace(t, dev, vel=vel, cmd=+5.0 * vel, spec=spec))    # a negative damper
    assert active["energy_injected_mj"] > M.ACTIVE_TOLERANCE_MJ and active["unstable"]
    gone = dev.copy()
    gone[:, 0] += np.linspace(0, 0.2, len(t))                          # slides out of the hole
    assert M.hole_metrics(_trace(t, gone, vel=vel, cmd=-5.0 * vel, spec=spec))["unstable"]
    assert M.hole_metrics(_trace(t, dev, vel=vel, cmd=-5.0 * vel, spec=spec, faults=1))["unstable"]


# ------------------------------------------------------------------------------ the figures
def test_fig6_deformation_keeps_the_peg_bounded_without_it_it_runs_away(tmp_path):
    """On the server loop (simulated time): the 1-DOF device, direct coupling, the peg engine
    behind the protocol with a 20 ms delay."""
    res = F.fig6(tmp_path, mode="simulated", quick=True)
    assert set(res) == {"rigid", "deformation"}
    rigid, d = res["rigid"], res["deformation"]
    assert rigid["unstable"] is True
    assert rigid["peak_excursion_mm"] > F.PEG_RUNAWAY_MM      # thrown out of the hole, into the end-stops
    assert rigid["faults"] >= 1                               # ... and the safety layer faded the device out
    assert d["unstable"] is False and d["faults"] == 0 and d["nonfinite"] == 0
    assert d["growth"] < F.PEG_GROWTH_LIMIT
    assert d["peak_excursion_mm"] < 40.0                      # bounded within two peg widths of travel
    assert d["mode"].startswith("simulated (server loop") and d["contact_frame"] == "engine"
    # the same verdicts in the proxy frame and on the model alone
    assert rigid["proxy_frame"]["unstable"] and not d["proxy_frame"]["unstable"]
    assert rigid["model_only"]["unstable"] and not d["model_only"]["unstable"]
    # the paper's rigid baseline runs without the passivity layer; with it, the layer holds the peg
    held = rigid["with_layer"]
    assert held["peak_excursion_mm"] < F.PEG_RUNAWAY_MM and held["faults"] == 0
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["deformation"]["unstable"] is False and saved["rigid"]["unstable"] is True
    assert (tmp_path / "fig6.png").stat().st_size > 10_000


def test_fig9_epsilon_keeps_both_walls_in_the_model_and_the_peg_tight(tmp_path):
    res = F.fig9(tmp_path, mode="simulated", quick=True)
    assert set(res) == {"IR", "LM0", "LM5"}
    lm0, lm5 = res["LM0"], res["LM5"]
    assert lm5["both_walls_fraction"] > 0.95                 # both walls always in the model
    assert lm0["both_walls_fraction"] < 0.05                 # active geometry: one wall at a time
    assert lm5["force_on_fraction"] > 0.9 > lm0["force_on_fraction"]
    assert lm5["peak_excursion_mm"] < 0.25 * lm0["peak_excursion_mm"]
    assert lm5["peak_excursion_mm"] < 1.0                    # K x 1 mm = 10 N > the 5 N hand: held by the walls
    assert not lm0["unstable"] and not lm5["unstable"] and res["IR"]["unstable"]
    # with the contacts in the proxy frame the delayed separations move the walls (measured, kept;
    # the deformation recovery needs the engine frame, so it does not act there)
    assert lm5["proxy_frame"]["peak_excursion_mm"] > 2 * lm5["peak_excursion_mm"]
    assert (tmp_path / "fig9.png").exists() and (tmp_path / "fig9_proxy_frame.png").exists()


def test_fig14_local_model_settles_at_the_wall(tmp_path):
    res = F.fig14(tmp_path, mode="simulated", quick=True)
    assert set(res) == {"IR", "LM0", "LM5"}
    for m in ("LM0", "LM5"):
        r = res[m]
        assert r["settled"], r
        assert r["limit_cycle_amplitude_mm"] < M.SETTLED_MM
        assert 0.0 <= r["wall_error_mm"] < 20.0              # felt at or beyond the wall, never short
        assert r["final_force_n"] == pytest.approx(-0.5, abs=0.01)
        assert r["faults"] == 0 and r["model_nonfinite"] == 0
        assert r["engine_frame"]["settled"]
    for m in res:
        for key in ("felt_wall_mm", "limit_cycle_amplitude_mm", "limit_cycle_rotation_deg", "energy_injected_mj"):
            assert key in res[m] and key in res[m]["engine_frame"]
    assert res["LM5"]["epsilon_mm"] == 5.0 and res["IR"]["controller"] == "direct"
    assert json.loads((tmp_path / "metrics.json").read_text()).keys() == res.keys()
    assert (tmp_path / "fig14.png").exists() and (tmp_path / "fig14_engine_frame.png").exists()
    # the felt-wall sweep: a contact predicted in time is felt at the wall, a late one beyond it
    sweep = {r["epsilon_mm"]: r for r in json.loads((tmp_path / "felt_wall_sweep.json").read_text())["rows"]}
    assert set(sweep) == {0.0, 5.0, 10.0}
    late, in_time = sweep[0.0], sweep[10.0]
    assert late["first_contact_mm_mean"] > in_time["first_contact_mm_mean"]           # learnt of it deeper
    assert abs(in_time["wall_error_mm_mean"]) < 1.5
    assert late["wall_error_mm_mean"] > 2.0 + in_time["wall_error_mm_mean"]
    assert min(r["felt_wall_mm"]["min"] for r in sweep.values()) >= M.WALL_Y_MM - 0.5   # never short of it
    # with deformation recovery (the server's default) the late contact is felt where it is too
    assert all(abs(r["recovered"]["wall_error_mm_mean"]) < 0.5 for r in sweep.values())
    assert (tmp_path / "fig14_felt_wall_vs_epsilon.png").exists()


def test_fig16_epsilon_reduces_drift_in_the_tight_hole(tmp_path):
    res = F.fig16(tmp_path, mode="simulated", quick=True)
    assert res["LM5"]["drift_mm"] < 0.5 * min(res["LM0"]["drift_mm"], res["IR"]["drift_mm"]), res
    assert res["LM5"]["x_travel_mm"] < 0.5 * res["LM0"]["x_travel_mm"]
    assert not any(res[m]["unstable"] for m in res)          # k = 4000: stable with all three (the paper's)
    for m in res:
        assert {"drift_mm", "rotation_deg", "unstable"} <= set(res[m])


def test_fig17_stiff_hole_only_the_local_model_is_stable(tmp_path):
    res = F.fig17(tmp_path, mode="simulated", quick=False)   # 10 s: the IR needs a few seconds to run away
    assert res["IR"]["unstable"] is True
    assert res["LM0"]["unstable"] is False and res["LM5"]["unstable"] is False
    assert res["LM5"]["drift_mm"] < res["LM0"]["drift_mm"]
    assert (tmp_path / "fig17.png").exists()


# ------------------------------------------------------------------------------ the command
def test_experiment_command_writes_metrics_and_refuses_bad_arguments(tmp_path, capsys):
    assert experiment_main(["fig9", "--out", str(tmp_path / "f9"), "--quick", "--quiet", "--mode", "simulated"]) == 0
    out = capsys.readouterr().out
    assert "fig9 LM5" in out and "metrics.json" in out
    assert json.loads((tmp_path / "f9" / "metrics.json").read_text())["LM5"]["unstable"] is False
    with pytest.raises(SystemExit) as exc:
        experiment_main(["fig99", "--out", str(tmp_path)])
    assert exc.value.code == 2
    with pytest.raises(SystemExit):
        experiment_main(["fig6"])                            # --out is required
