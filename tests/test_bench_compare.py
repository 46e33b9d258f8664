"""benchmarks/compare.py: rows of either tree matched by their text fields, medians, the ratio."""
from __future__ import annotations

import json

import pytest

from hapticproxy.benchmarks import compare as C


def test_rows_are_read_from_every_json_shape_a_bench_prints():
    rows = [{"tool": "planar", "contacts": 8, "numba_median_us": 4.0}]
    assert C._rows(json.dumps(rows)) == rows
    assert C._rows(json.dumps({"rows": rows, "run": {}})) == rows
    jsonl = "\n".join([json.dumps({"run": {"date": "x"}}), json.dumps(rows[0]), "a table line"])
    assert rows[0] in C._rows(jsonl)


def test_times_are_keyed_by_label_and_repeated_labels_stay_apart():
    t = C._times([{"tool": "1dof", "contacts": 8, "numba_median_us": 3.0, "steps": 100, "ok": True},
                  {"tool": "1dof", "contacts": 8, "numba_median_us": 5.0}])
    assert t == {("tool=1dof contacts=8", "numba_median_us"): 3.0,
                 ("tool=1dof contacts=8 #2", "numba_median_us"): 5.0}


def test_a_report_with_distributions_and_row_lists_gives_every_figure():
    """bench loop prints one report: distributions of the real loop, and a list of update-step rows."""
    report = {"rate_hz": 1000.0, "lateness_us": {"p50": 1.0, "p99": 40.0}, "steps": 100, "machine": "x86_64",
              "clock": "thread CPU time",
              "update_steps": [{"tool": "planar", "contacts": 8, "apply_us": {"n": 30, "p99": 90.0}}]}
    t = C._times(C._rows(json.dumps(report)))
    assert t[("-", "lateness_us.p99")] == 40.0 and t[("-", "lateness_us.p50")] == 1.0
    assert t[("tool=planar contacts=8", "apply_us.p99")] == 90.0 and ("-", "steps") not in t
    assert ("tool=planar contacts=8", "apply_us.n") not in t  # a count, not a time


def test_compare_takes_medians_of_alternating_rounds(monkeypatch, tmp_path):
    calls = []
    figures = {"base": iter([10.0, 30.0, 20.0]), "this": iter([5.0, 6.0, 100.0])}

    def fake(tree, name, args, timeout_s):
        which = tree.name
        calls.append(which)
        return {("tool=x", "numba_median_us"): next(figures[which])}

    monkeypatch.setattr(C, "run_bench", fake)
    rows = C.compare(tmp_path / "base", tmp_path / "this", ["model"], 3, 10.0, log=lambda *a, **k: None)
    assert calls == ["base", "this"] * 3  # alternating: load that comes and goes hits both
    assert rows == [{"bench": "model", "row": "tool=x", "figure": "numba_median_us", "baseline_us": 20.0,
                     "this_us": 6.0, "ratio": 0.3}]


def test_a_missing_baseline_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        C.main(["--baseline", str(tmp_path)])
    assert e.value.code == 2 and "no .venv/bin/hapticproxy" in capsys.readouterr().err


def test_the_table_shows_both_figures_and_the_ratio(monkeypatch, tmp_path, capsys):
    base = tmp_path / "base"
    (base / ".venv" / "bin").mkdir(parents=True)
    (base / ".venv" / "bin" / "hapticproxy").write_text("")
    monkeypatch.setattr(C, "run_bench", lambda tree, name, args, timeout_s: {
        ("tool=planar contacts=8", "numba_median_us"): 4.0 if tree.name == "base" else 3.0})
    assert C.main(["--baseline", str(base), "--benches", "model", "--rounds", "1"]) == 0
    out = capsys.readouterr().out
    assert "tool=planar contacts=8" in out and "4.000" in out and "3.000" in out and "0.75" in out
