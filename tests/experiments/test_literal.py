"""The paper's eq. 6 read literally (the epsilon-inflated tool rendered, new contacts by eq. 6):
a reproduction option of the experiments that gives the paper's Fig. 14 "wall felt short of
where it is", and why the server does not read it so (Fig. 16 ejects the peg). Never a setting."""
from __future__ import annotations

import json

import pytest

from hapticproxy.experiments import figures as F
from hapticproxy.experiments import metrics as M
from hapticproxy.server import config as cfgmod
from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec


def test_literal_reading_feels_the_wall_short_and_ejects_the_peg_from_the_hole(tmp_path):
    res = F.paper_literal(tmp_path, quick=True)
    rows = {(r["figure"], r["method"], r["reading"]): r for r in res["rows"]}
    lit, notes = rows[("fig14", "LM5", "paper-literal")], rows[("fig14", "LM5", "notes")]
    # epsilon 5 mm rendered: the wall felt about epsilon before it (the paper's 118 mm)
    assert lit["felt_wall_mm"]["max"] < M.WALL_Y_MM - 3.0
    assert notes["felt_wall_mm"]["min"] >= M.WALL_Y_MM - 0.5            # the server's reading: never short
    assert lit["settled"]["true"] == lit["settled"]["of"]
    # ... and in the tight hole the inflated geometry, rendered, throws the peg out
    assert rows[("fig16", "LM5", "paper-literal")]["unstable"]["true"] == rows[("fig16", "LM5", "paper-literal")]["unstable"]["of"]
    assert rows[("fig16", "LM5", "notes")]["unstable"]["true"] == 0
    saved = json.loads((tmp_path / "literal.json").read_text())
    assert len(saved["rows"]) == len(res["rows"])
    assert "paper-literal" in (tmp_path / "literal.md").read_text()


def test_the_literal_reading_is_not_a_server_setting():
    assert "paper-literal" not in cfgmod.POLICIES
    with pytest.raises(ValueError, match="policy"):
        LocalModel(ToolSpec.planar(0.25, 1e-4), ContactParams(4000.0, 30.0), policy="paper-literal")
    with pytest.raises(ValueError):
        cfgmod.load({"model": {"policy": "paper-literal"}})
