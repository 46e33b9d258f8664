"""``hapticproxy bench faults``' rows for the safety filter and the fault policy (``faults_safety``),
each run here as the bench runs it: the server's loop in simulated time, every promise checked at
every step of its telemetry; ``accurate`` on a loaded machine is real time and runs with the slow
sweeps (``-m slow``)."""
from __future__ import annotations

import pytest

from hapticproxy.benchmarks import faults_safety as fs

SIMULATED = [c for c in fs.cases() if c.kind != "accurate"]


@pytest.mark.parametrize("case", SIMULATED, ids=lambda c: c.kind)
def test_each_safety_row_keeps_every_promise(case):
    row = fs.run_case(case)
    assert "error" not in row, row
    assert row["violations"] == 0, (row["case"], row["broken"])
    if case.kind in ("torque", "diagonal", "axis1d"):
        assert row["cap_reached"]  # the row meets the cap, so it shows the cap holding


@pytest.mark.slow
def test_accurate_on_a_loaded_machine_never_latches():
    from hapticproxy.benchmarks import bench_faults

    row = fs.run_case([c for c in fs.cases() if c.kind == "accurate"][0], bench_faults)
    assert row["violations"] == 0, row


def test_the_checker_sees_each_broken_promise():
    """``check_filter`` on hand-made telemetry: one row per broken promise."""
    import numpy as np

    from hapticproxy.server.shm import NTEL, TEL

    lim = {"force_cap_n": 10.0, "torque_cap_n_m": 0.5, "rate_limit_n_per_step": 1.0,
           "torque_rate_n_m_per_step": 0.05, "ramp_per_step": 0.002}

    def rows(fy, g, tz=None):
        r = np.zeros((len(fy), NTEL))
        r[:, TEL["cmd_fy"]] = fy
        r[:, TEL["gain"]] = g
        if tz is not None:
            r[:, TEL["cmd_tz"]] = tz
        return r

    def broken(r):
        b = {}
        fs.check_filter(r, lim, b)
        return b

    assert broken(rows([0.0, 0.5, 1.0], [1.0, 1.0, 1.0])) == {}
    assert "force norm over the cap" in broken(rows([9.5, 10.2, 10.0], [1.0, 1.0, 1.0]))
    assert "force step over the rate limit" in broken(rows([0.0, 1.5], [1.0, 1.0]))
    assert "torque step over its rate limit" in broken(rows([0.0, 0.0], [1.0, 1.0], tz=[0.0, 0.08]))
    assert "a fade pushed harder than its envelope" in broken(rows([3.0, 2.9], [1.0, 0.9]))
    assert "a ramp grew faster than its slope" in broken(rows([0.0, 0.05], [0.0, 0.002]))
