"""One experiment on the real system: the server process at 512 Hz and the stub client over UDP
on 127.0.0.1 (what ``hapticproxy experiment fig14`` runs per method). Counts and positions are
asserted, never wall-clock figures; every process started is stopped."""
from __future__ import annotations

import multiprocessing

from hapticproxy.experiments import metrics as M
from hapticproxy.experiments.figures import fig14_spec
from hapticproxy.experiments.harness import run_realtime


def test_static_contact_on_the_real_server_over_udp():
    spec = fig14_spec("LM5", "realtime", True).but(seconds=2.5)
    tr = run_realtime(spec)
    assert multiprocessing.active_children() == []         # the loop process was stopped
    assert tr.mode == "realtime" and tr.faults == 0 and tr.model_nonfinite == 0
    assert tr.extra["updates"] > 20                       # the environment at 30-60 Hz for seconds
    assert tr.contacts.max() >= 2                         # the peg's bottom face on the wall
    m = M.static_contact_metrics(tr)
    assert 0.0 <= m["wall_error_mm"] < 25.0               # the wall is felt at or just beyond 124 mm
    assert m["first_contact_mm"] is not None and m["first_contact_mm"] > 100.0
    assert abs(m["final_force_n"] + 0.5) < 0.05            # the wall balances the 0.5 N push
    assert len(tr.t_s) > 100


def test_peg_on_the_real_server_through_a_delaying_relay():
    """Fig. 9's LM5 on the real system: the 1-DOF device at 512 Hz, the peg engine at 50 Hz over
    UDP through an impairing relay that delays every ContactUpdate by 20 ms."""
    from hapticproxy.experiments.figures import PegView, peg_metrics, peg_spec

    spec = peg_spec("LM5", "deformation", 0.005, "realtime", True).but(seconds=3.0)
    tr = run_realtime(spec)
    assert multiprocessing.active_children() == []         # the loop process was stopped
    assert tr.faults == 0 and tr.model_nonfinite == 0
    assert tr.extra["updates"] > 60                       # 50 Hz for seconds
    m = peg_metrics(PegView.of_trace(tr), 3.0)
    assert m["both_walls_fraction"] > 0.95                # epsilon keeps both walls in the model
    assert m["peak_excursion_mm"] < 1.0                   # the peg stays tight in its hole
    assert not m["unstable"]
