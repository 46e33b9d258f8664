"""The whole server loop, in simulated time, fed by engines that misreport contacts the way real
ones do (issue 13, section 4): normals that reverse, keys that get renumbered. The force on the
hand must not step by more than the rate limit allows (here: not at all) and must never point
into the surface."""
from __future__ import annotations

import numpy as np
import pytest

from hapticproxy.experiments import figures as F
from hapticproxy.experiments.harness import RECOVERY_OFF, Hand, RunSpec, run_simulated

FROM_S = 2.0   # engine time at which the misreports start: the push has long settled
# without deformation recovery: nothing else changes the force once the push has settled (with
# it, a deformed contact is still being recovered at 0.2 N per step at most)
REC = RECOVERY_OFF


def _wall_run(misreport: str, **kw):
    spec = RunSpec.for_method("LM5", contact_frame="engine", rate_hz=1000.0, seconds=3.5, seed=2,
                              hand=Hand("constant", (0.0, 0.5, 0.0), start_s=0.6), misreport=misreport,
                              misreport_from_s=FROM_S, misreport_every=3, recovery=REC, **kw)
    return run_simulated(spec)


def _peg_run(misreport: str):
    spec = F.peg_spec("LM0", "lm0", 0.0, "simulated", True).but(
        hand=Hand("constant", (0.5, 0.0, 0.0), start_s=0.6), seconds=3.5, misreport=misreport,
        misreport_from_s=FROM_S, misreport_every=3, recovery=REC)
    return run_simulated(spec)


def _window(tr):
    """From the first misreported update on (the server has the engine's time axis offset by the
    engagement; the misreports start at FROM_S of engine time, well after the hand)."""
    return tr.t_s >= FROM_S - 0.2


@pytest.mark.parametrize("misreport", ["flip", "flip-hold", "rekey"])
def test_planar_wall_force_is_untouched_by_misreports(misreport):
    tr = _wall_run(misreport)
    assert tr.extra["misreported_updates"] >= 10
    c = tr.extra["model"]
    assert (c["flips_refused"] if misreport.startswith("flip") else c["rekeyed"]) >= tr.extra["misreported_updates"]
    w = _window(tr)
    fy = tr.env[w, 1]                                   # the wall's normal is -y (towards the tool)
    assert np.max(fy) <= 0.0                            # never a pull into the wall
    steps = np.abs(np.diff(tr.env[w, :2], axis=0)).max()
    pen_steps = np.abs(np.diff(tr.penalty[w, :2], axis=0)).max()
    assert steps < 0.01 and pen_steps < 0.01            # the rate limit is 1 N per step; no step at all
    assert np.all(np.abs(fy + 0.5) < 0.01)             # still carrying the 0.5 N push: no drop, no overshoot
    assert np.ptp(tr.dev[w, 1]) < 1e-5                  # the device does not move


@pytest.mark.parametrize("misreport", ["flip", "rekey"])
def test_misreports_while_a_deformation_is_recovered(misreport):
    # the same with the server's deformation recovery on, while it brings the peg out of a late
    # wall (seed 2: 3.3 mm deep, recovered from 1.45 s on): the force changes at most at the
    # recovery's bound (200 N/s, 0.2 N per step) and never pulls into the wall
    tr = run_simulated(
        RunSpec.for_method("LM5", contact_frame="engine", rate_hz=1000.0, seconds=2.5, seed=2,
                           hand=Hand("constant", (0.0, 0.5, 0.0), start_s=0.6), misreport=misreport,
                           misreport_from_s=1.4, misreport_every=2))
    assert tr.extra["misreported_updates"] >= 10
    w = tr.t_s >= 1.4
    assert np.any(tr.recovering[w] > 0)
    assert np.max(tr.env[w, 1]) <= 0.0
    assert np.abs(np.diff(tr.penalty[w, :2], axis=0)).max() < 0.2 + 0.01


@pytest.mark.parametrize("misreport", ["flip", "flip-hold", "rekey"])
def test_single_wall_1dof_peg_force_is_untouched_by_misreports(misreport):
    # one contact carries the whole push: a reversed normal would turn +0.5 N into a 0.5 N pull
    tr = _peg_run(misreport)
    assert tr.extra["misreported_updates"] >= 10
    w = _window(tr)
    fx = tr.env[w, 0]                                   # the right wall's normal is -x
    assert np.max(fx) <= 0.0
    assert np.abs(np.diff(fx)).max() < 0.01
    assert np.all(np.abs(fx + 0.5) < 0.01)


def test_a_run_without_the_penalty_column_has_none():
    # run_simulated(record_penalty=False) used to fail slicing the column it had not recorded
    spec = RunSpec(seconds=0.3, hand=Hand("constant", (0.0, 0.5, 0.0), start_s=0.1))
    tr = run_simulated(spec, record_penalty=False)
    assert tr.penalty is None and len(tr.t_s) > 0 and tr.update_step is not None
    assert len(tr.update_step) == len(tr.t_s)
