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
    try:
        assert tr.mode == "realtime" and tr.faults == 0 and tr.model_nonfinite == 0
        assert tr.extra["updates"] > 20                       # the environment at 30-60 Hz for seconds
        assert tr.contacts.max() >= 2                         # the peg's bottom face on the wall
        m = M.static_contact_metrics(tr)
        assert 0.0 <= m["wall_error_mm"] < 25.0               # the wall is felt at or just beyond 124 mm
        assert m["first_contact_mm"] is not None and m["first_contact_mm"] > 100.0
        assert abs(m["final_force_n"] + 0.5) < 0.05            # the wall balances the 0.5 N push
        assert len(tr.t_s) > 100
    finally:
        assert multiprocessing.active_children() == []     # the loop process was stopped
