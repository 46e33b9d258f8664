"""``hapticproxy bench passivity``: its rows and summary (structure), and what they must show in
simulated time: the adversarial floor gives the hand far more than the budget with the layer
off, and at most the budget plus 1 mJ with it on (no wall clock anywhere)."""
from __future__ import annotations

import json

import pytest

from hapticproxy.benchmarks import bench_passivity as bp

KEYS = {"hand", "layer", "seed", "seconds", "rate_hz", "delay_ms", "jumps", "budget_j", "given_max_j", "given_end_j",
        "excess_j", "tank_low_j", "tank_end_j", "limited_steps", "steps", "faults", "rise_mm"}


def _run(capsys, *argv):
    assert bp.main(["--json", *argv]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    return lines[0], lines[1:-1], lines[-1]["summary"]


def test_rows_and_summary_and_the_layer_keeps_the_budget(capsys):
    head, rows, summary = _run(capsys, "--seeds", "1", "--seconds", "2.5", "--delays-ms", "0")
    assert set(head["run"]) == {"machine", "date_utc"}
    assert len(rows) == 4 and all(set(r) == KEYS for r in rows)
    assert {(r["hand"], r["layer"]) for r in rows} == {(h, s) for h in bp.HANDS for s in ("on", "off")}
    assert set(summary) == {"push/off", "push/on", "grip/off", "grip/on"}
    by = {(r["hand"], r["layer"]): r for r in rows}
    for hand in bp.HANDS:
        off, on = by[(hand, "off")], by[(hand, "on")]
        assert off["jumps"] >= 3 and off["faults"] == on["faults"] == 0
        assert off["excess_j"] > 0.01 and off["limited_steps"] == 0  # the floor pumps the hand
        assert on["excess_j"] <= 1e-3 and on["limited_steps"] > 0  # the layer holds the budget
        assert on["rise_mm"] < off["rise_mm"]
    assert summary["grip/on"]["runs_over_1mj"] == 0 and summary["grip/off"]["runs_over_1mj"] == 1


def test_a_delayed_engine_changes_nothing_about_the_promise():
    on = bp.run("grip", True, seed=1, seconds=2.5, delay_ms=100.0)
    assert on["delay_ms"] == 100.0 and on["excess_j"] <= 1e-3


@pytest.mark.parametrize("argv", [["--hands", "fist"], ["--seeds", "0"], ["--seconds", "0.5"], ["--delays-ms", "x"]])
def test_bad_arguments_are_usage_errors(argv, capsys):
    assert bp.main(argv) == 2
    assert capsys.readouterr().err.startswith("hapticproxy bench passivity: --")


@pytest.mark.slow
def test_the_sweep_has_no_run_above_the_budget_plus_1mj(capsys):
    _, rows, summary = _run(capsys, "--seeds", "10", "--seconds", "5", "--delays-ms", "0,50,100,300")
    assert all(summary[f"{h}/on"]["runs_over_1mj"] == 0 for h in bp.HANDS), summary
    assert len(rows) == 2 * 4 * 2 * 10
