"""The paper's Fig. 6: 1 kg peg in an exactly fitting hole, both walls reported 20 ms late,
K = 10000 N/m, B = 15 N s/m, 5 N sinusoidal hand force at 1 Hz (our choice: the paper's
frequency is garbled), direct coupling. Without deformation the hand's motion grows unstable;
with proxy deformation it stays bounded."""
from hapticproxy.experiments.peg1d import FIG6_FORCE_HZ, PEG_HALF_WIDTH_M, simulate_peg1d


def test_rigid_policy_grows_unstable():
    run = simulate_peg1d("rigid", duration_s=5.0)
    assert FIG6_FORCE_HZ == 1.0
    assert run.unstable
    assert run.growth > 10.0
    assert run.updates >= 240                  # 50 Hz environment over 5 s


def test_proxy_deformation_stays_bounded():
    run = simulate_peg1d("deformation", duration_s=5.0)
    assert not run.unstable
    assert run.growth < 1.5
    # bounded near the walls' static compliance (5 N / 10000 N/m = 0.5 mm), far inside the peg
    assert abs(run.x_hand_m).max() < 0.2 * PEG_HALF_WIDTH_M
    assert run.nonfinite == 0
