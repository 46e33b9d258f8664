"""``bench loop``'s update-step measurement sorts each step by what it did with an update: every
applied update has one receiving, one staging and one applying step (its tick applies it, its
Python part acknowledges it; never housekeeping with them), so the figures it prints are of those
steps and no others."""
from __future__ import annotations

from hapticproxy.benchmarks.update_steps import measure


def test_each_update_has_a_receive_a_stage_and_an_apply_step():
    r = measure("planar", steps=400, every=16, contacts=4)
    assert r["faults"] == 0 and r["updates"] >= 20
    n = {k: (r[f"{k}_us"] or {"n": 0})["n"] for k in ("receive", "stage", "apply", "housekeeping", "other")}
    # the first three of each kind are dropped as warm-up when there are more than ten
    assert n["apply"] == n["stage"] == r["updates"] - 3, n
    assert abs(n["receive"] - n["apply"]) <= 1, n
    assert n["housekeeping"] > 0 and n["other"] > 10 * n["apply"]
    assert set(r["p50_over_plain"]) == {"receive", "stage", "apply"}
