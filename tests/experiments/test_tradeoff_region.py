"""``hapticproxy experiment tradeoff --region-only``: the stable-region grid alone, a part of it,
with the server's current defaults (the plumbing; the sweep itself is the ``slow`` test and the
quick trade-off in test_tradeoff.py)."""
from __future__ import annotations

import json

import pytest

from hapticproxy.experiments import cli
from hapticproxy.experiments import tradeoff as T
from hapticproxy.server import config as cfgmod


def _fake_region(calls):
    """A stand-in for the sweep: one row per (controller, rate) asked for, recording the call."""
    def stable_region(*, quick, seeds, log=None, controllers=None, rates=None, layer=None):
        calls.append({"quick": quick, "seeds": tuple(seeds), "controllers": controllers, "rates": rates,
                      "layer": layer})
        rows, rs = T.region_rows(controllers, rates, quick=quick)
        return [{"controller": n, "rate_hz": r, "smallest_stable_stiffness_n_per_m": 1000.0,
                 "largest_stable_stiffness_n_per_m": 2000.0 * (i + 1), "smallest_refused_stiffness_n_per_m": None,
                 "wall_s": 0.0, "tried": []} for i, (n, _) in enumerate(rows) for r in rs]
    return stable_region


def test_region_only_runs_only_the_region_with_the_rows_and_rates_asked(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(T, "stable_region", _fake_region(calls))
    monkeypatch.setattr(T, "run_tradeoff", lambda *a, **k: pytest.fail("the whole trade-off ran"))
    rc = cli.main(["tradeoff", "--region-only", "--out", str(tmp_path), "--quiet",
                   "--region-controllers", "four_channel;IR (direct, rigid, eps 0, eq. 1)",
                   "--region-rates", "512,4000"])
    assert rc == 0
    assert calls == [{"quick": False, "seeds": T.REGION_SEEDS, "controllers": ("four_channel",
                      "IR (direct, rigid, eps 0, eq. 1)"), "rates": (512.0, 4000.0), "layer": None}]
    saved = json.loads((tmp_path / "stable_region.json").read_text())
    assert [(e["controller"], e["rate_hz"]) for e in saved["stable_region"]] == [
        ("four_channel", 512.0), ("four_channel", 4000.0),
        ("IR (direct, rigid, eps 0, eq. 1)", 512.0), ("IR (direct, rigid, eps 0, eq. 1)", 4000.0)]
    assert saved["settings"] == T.region_settings()
    assert (tmp_path / "stable_region.png").stat().st_size > 100
    assert not (tmp_path / "tradeoff.json").exists()
    out = capsys.readouterr().out
    md = (tmp_path / "stable_region.md").read_text()
    assert "| four_channel | 1000 - **2000** | 1000 - **2000** |" in md and md.strip() in out


def test_region_only_without_a_part_runs_the_whole_grid(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(T, "stable_region", _fake_region(calls))
    assert cli.main(["tradeoff", "--region-only", "--quick", "--out", str(tmp_path), "--quiet"]) == 0
    assert calls == [{"quick": True, "seeds": T.QUICK_SEEDS, "controllers": None, "rates": None, "layer": None}]
    saved = json.loads((tmp_path / "stable_region.json").read_text())
    assert len(saved["stable_region"]) == len(T.REGION_CONTROLLERS) * len(T.QUICK_REGION_RATES)


@pytest.mark.parametrize("argv, words", [
    (["fig6", "--region-only"], "tradeoff experiment only"),
    (["tradeoff", "--layer", "off"], "--layer applies to the zwidth experiment and tradeoff --region-only"),
    (["tradeoff", "--region-rates", "512"], "need --region-only"),
    (["tradeoff", "--region-only", "--region-rates", "700"], "700 Hz not in the grid"),
    (["tradeoff", "--region-only", "--region-rates", "fast"], "expected rates in Hz"),
    (["tradeoff", "--region-only", "--region-controllers", "pid"], "'pid' not in the grid"),
])
def test_bad_region_arguments_exit_2_naming_the_option(tmp_path, monkeypatch, capsys, argv, words):
    def ran(*a, **k):
        raise AssertionError("a run started: the arguments were not refused")

    for name in ("run_tradeoff", "run_region", "stable_region"):
        monkeypatch.setattr(T, name, ran)
    from hapticproxy.experiments import figures
    monkeypatch.setitem(figures.FIGURES, "fig6", ran)
    with pytest.raises(SystemExit) as e:
        cli.main(argv + ["--out", str(tmp_path)])
    assert e.value.code == 2
    assert words in capsys.readouterr().err


def test_the_region_runs_with_the_servers_current_defaults(tmp_path):
    # nothing in the region's runs pins the layer, the integrator or the coupling damping: the
    # server's defaults apply, and the recorded settings are those defaults
    d = cfgmod.load({})
    s = T.region_settings()
    assert s["passivity_enabled"] == d["passivity"]["enabled"]
    assert s["controller_damping_n_s_per_m"] == d["controller"]["damping_n_s_per_m"]
    from hapticproxy.server.model.model import LocalModel, ToolSpec
    assert s["integrator"] == LocalModel(ToolSpec.planar(0.1, 1e-4), warm=False).integrator
    for name, kw in T.REGION_CONTROLLERS:
        spec = T.replace(T.BASE, **kw).spec("hole_long", 1, False)
        assert spec.recovery == () and spec.reading == "", name       # the model as the server builds it
        settings = spec.settings_dict("mem://x", 1, tmp_path)
        assert settings["passivity"] == {}, name
        assert set(settings["controller"]) == {"type"}, name


def test_layer_off_reaches_every_run_of_the_region(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(T, "stable_region", _fake_region(calls))
    assert cli.main(["tradeoff", "--region-only", "--layer", "off", "--region-rates", "1000", "--out", str(tmp_path),
                     "--quiet"]) == 0
    assert calls[0]["layer"] == "off" and calls[0]["rates"] == (1000.0,)
    saved = json.loads((tmp_path / "stable_region.json").read_text())
    assert saved["settings"]["passivity_enabled"] is False and saved["settings"]["layer"] == "off"
    # ... and the run's config carries it to the server's [passivity] table
    for layer, table in ((None, {}), ("off", {"enabled": False}), ("on", {"enabled": True})):
        spec = T.replace(T.BASE, layer=layer).spec("wall", 1, True)
        assert spec.settings_dict("mem://x", 1, tmp_path)["passivity"] == table, layer


def test_a_layer_other_than_on_or_off_is_refused_before_any_run():
    with pytest.raises(ValueError, match="layer: expected on, off"):
        T.stable_region(quick=True, seeds=(1,), layer="maybe")


def test_the_scan_runs_each_asked_cell_with_the_layer_and_stops_two_unstable_above_the_band(monkeypatch):
    seen = []
    unstable_k = {1000.0, 20000.0, 50000.0}       # too soft, then two unstable in a row above the band

    def evaluate(cfg, *, seeds, quick, scenarios, model_timing_every):
        seen.append((cfg.controller, cfg.rate_hz, cfg.stiffness_n_per_m, cfg.layer, model_timing_every, scenarios))
        bad = cfg.stiffness_n_per_m in unstable_k
        return {"unstable": bad, "refused": False, "energy_injected_mj": 0.0, "loop_exceptions": []}

    monkeypatch.setattr(T, "evaluate", evaluate)
    region = T.stable_region(quick=False, seeds=(1,), controllers=("direct",), rates=(2000.0,), layer="off")
    assert [(e["controller"], e["rate_hz"]) for e in region] == [("direct", 2000.0)]
    e = region[0]
    assert (e["smallest_stable_stiffness_n_per_m"], e["largest_stable_stiffness_n_per_m"]) == (2000.0, 10000.0)
    assert [s[2] for s in seen] == [1000.0, 2000.0, 4000.0, 10000.0, 20000.0, 50000.0]
    assert all(s[:2] == ("direct", 2000.0) and s[3] == "off" and s[4] == 0 and s[5] == ("wall", "hole_long")
               for s in seen)
