"""``control._diverged``: what the haptic step does the step the model flags its integration as
diverged (``model.layout.DIVERGE_STEPS`` velocity reversals in a row), every case of its contract."""
from __future__ import annotations

import numpy as np
import pytest

from hapticproxy.server import control as ctl
from hapticproxy.server.model.layout import DIVERGE_STEPS, K_OSC_RUN, NCOUNT


@pytest.mark.parametrize("run", [0, 1, DIVERGE_STEPS - 1, DIVERGE_STEPS, DIVERGE_STEPS + 1, 10 * DIVERGE_STEPS])
@pytest.mark.parametrize("rc", [ctl.RC_OK, ctl.RC_SPEED])
def test_the_flag_step_drops_the_target_and_reports_once(run, rc):
    cs = np.zeros(ctl.NCS)
    cs[ctl.CS_TARGET] = 1.0
    cnt = np.zeros(NCOUNT, dtype=np.int64)
    cnt[K_OSC_RUN] = run
    out = ctl._diverged(cs, cnt, rc)
    flagged = run == DIVERGE_STEPS
    # the target drops at the flag step only (the fault's fade then belongs to the lifecycle)
    assert cs[ctl.CS_TARGET] == (0.0 if flagged else 1.0)
    # reported once per run, and never over a fault the step already had
    assert out == (ctl.RC_DIVERGED if flagged and rc == ctl.RC_OK else rc)
