"""Rules of the test suite itself (CONTRIBUTING.md): no assertion inside a ``finally`` block (it
hides the failure that got there, or fails a test that passed for the cleanup's sake), and the
real-time suite is out of the default run and a step of ``.ci/run`` of its own."""
from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_no_assert_inside_a_finally_block():
    found = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Try):
                for stmt in node.finalbody:
                    found += [f"{path.relative_to(ROOT)}:{n.lineno}" for n in ast.walk(stmt) if isinstance(n, ast.Assert)]
    assert not found, f"assert inside finally: {found}"


def test_the_realtime_suite_is_out_of_the_default_run_and_a_ci_step():
    opts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    assert "not realtime" in opts["addopts"] and "not slow" in opts["addopts"]
    assert any(m.startswith("realtime:") for m in opts["markers"])
    ci = (ROOT / ".ci" / "run").read_text()
    assert "sh run.sh test -m realtime" in ci
    # it is there: tests carry the marker
    marked = [p for p in (ROOT / "tests").rglob("test_*.py") if "mark.realtime" in p.read_text()]
    assert len(marked) >= 3, marked
