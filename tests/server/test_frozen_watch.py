"""``devices.frozen.watch``: its contract, over random sequences of readings and commands, against
a reference written from the contract's words (not from the kernel), and the drivers that run it."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hapticproxy.server.devices import frozen as fz

WINDOW_NS = 5_000_000  # five steps of 1 ms
FMIN = 0.25


def _arrays(window_ns=WINDOW_NS, fmin=FMIN, po=3, so=2):
    fp = np.full(po + fz.NFP + 2, -7.0)  # embedded at an offset, as the controller does
    fs = np.full(so + fz.NFS + 2, -7.0)
    fz.set_parameters(fp, po, frozen_s=window_ns * 1e-9, min_force_n=fmin)
    fz.reset(fs, so)
    return fp, po, fs, so


def reference(steps, window_ns=WINDOW_NS, fmin=FMIN):
    """The contract in plain words: True at step i when, for every step j of a run ending at i
    that began at t0 with now - t0 >= window, the reading (position and velocity) equals the one
    before it and the command's force norm is at least fmin."""
    out = []
    for i, (pos, force, now) in enumerate(steps):
        ok = False
        if window_ns > 0:
            k = i  # walk back over the run: identical readings under force
            while k >= 1 and steps[k][0] == steps[k - 1][0] and math.hypot(*steps[k][1]) >= fmin:
                k -= 1
            # the run's first step is k + 1 (the first identical reading under force)
            if k < i:
                ok = now - steps[k + 1][2] >= window_ns
        out.append(ok)
    return out


_pos = st.sampled_from([(0.0, 0.0, 0.0), (0.01, 0.0, 0.0), (0.0, 0.0, 5e-324), (0.0, -0.0, 0.0), (0.01, 0.0, 0.0)])
_vel = st.sampled_from([(0.0, 0.0, 0.0), (0.0, 6e-15, 0.0), (0.0, 0.0, 0.0), (-1e-300, 0.0, 0.0)])
_force = st.sampled_from([(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.0, 0.0, -0.25), (0.2, 0.1, 0.0), (0.1, 0.1, 0.1),
                          (0.0, 0.24999, 0.0)])


@settings(max_examples=400, derandomize=True, deadline=None)
@given(st.lists(st.tuples(st.tuples(_pos, _vel), _force, st.integers(1, 8), st.integers(0, 2)), min_size=1,
                max_size=12))
def test_the_watch_keeps_its_contract(segments):
    """Runs of identical readings under force (each segment holds one reading and one command for
    1-8 steps), broken by a moved position or velocity component (a denormal on one axis; -0.0
    equals 0.0), a weak command, or skipped periods (the time step varies): trips exactly when the
    reference says."""
    fp, po, fs, so = _arrays()
    steps, now = [], 1_000_000_000
    for reading, force, n, skip in segments:
        for _ in range(n):
            now += 1_000_000 * (1 + skip)
            steps.append((reading, force, now))
    want = reference(steps)
    got = []
    for (pos, vel), force, t in steps:
        row = np.zeros(20)
        row[3:] = 0.123  # orientation, angular velocity and the rest do not count
        row[0:3], row[7:10] = pos, vel
        cmd = np.array([*force, 9.0, 9.0, 9.0])  # torque does not count
        got.append(bool(fz.watch(fp, po, fs, so, row, cmd, t)))
    assert got == want


def test_the_sequences_reach_the_window():
    """The property test's strategy makes runs long enough to trip (not only their absence)."""
    seen = []

    @settings(max_examples=200, derandomize=True, deadline=None)
    @given(st.lists(st.tuples(st.tuples(_pos, _vel), _force, st.integers(1, 8), st.integers(0, 2)), min_size=1,
                    max_size=12))
    def count(segments):
        steps, now = [], 0
        for reading, force, n, skip in segments:
            for _ in range(n):
                now += 1_000_000 * (1 + skip)
                steps.append((reading, force, now))
        seen.append(any(reference(steps)))

    count()
    assert sum(seen) > 20


def test_off_never_trips_and_the_neighbours_are_untouched():
    fp, po, fs, so = _arrays(window_ns=0)
    before_p, before_s = fp.copy(), fs.copy()
    row, cmd = np.zeros(20), np.array([5.0, 0, 0, 0, 0, 0])
    assert not any(fz.watch(fp, po, fs, so, row, cmd, t) for t in range(0, 10**9, 10**6))
    fp, po, fs, so = _arrays()
    for t in range(0, 20_000_000, 1_000_000):
        fz.watch(fp, po, fs, so, row, cmd, t)
    assert np.all(fp[:po] == -7.0) and np.all(fp[po + fz.NFP:] == -7.0)
    assert np.all(fs[:so] == -7.0) and np.all(fs[so + fz.NFS:] == -7.0)
    del before_p, before_s


def test_a_nan_reading_never_makes_a_run():
    fp, po, fs, so = _arrays()
    row, cmd = np.full(20, math.nan), np.array([5.0, 0, 0, 0, 0, 0])
    assert not any(fz.watch(fp, po, fs, so, row, cmd, t) for t in range(0, 50_000_000, 1_000_000))


def test_exactly_at_the_window_and_not_one_step_before():
    fp, po, fs, so = _arrays()
    row, cmd = np.zeros(20), np.array([0.0, FMIN, 0, 0, 0, 0])
    got = [fz.watch(fp, po, fs, so, row, cmd, t * 1_000_000) for t in range(8)]
    # t=0: the first reading (the state was NaN); t=1: the run begins; t=6: 5 ms later
    assert got == [False] * 6 + [True, True]


def test_a_reset_starts_over():
    fp, po, fs, so = _arrays()
    row, cmd = np.zeros(20), np.array([1.0, 0, 0, 0, 0, 0])
    for t in range(10):
        last = fz.watch(fp, po, fs, so, row, cmd, t * 1_000_000)
    assert last
    fz.reset(fs, so)
    assert not fz.watch(fp, po, fs, so, row, cmd, 10_000_000)


@pytest.mark.parametrize("bad", [(-1.0, 0.25), (math.nan, 0.25), (0.5, 0.0), (0.5, math.inf)])
def test_parameters_are_checked(bad):
    with pytest.raises(ValueError):
        fz.set_parameters(np.zeros(2), 0, frozen_s=bad[0], min_force_n=bad[1])


def test_the_default_force_counts_on_a_weak_device():
    assert fz.min_force_n(0.0, 0.88) == pytest.approx(0.22)  # a Touch: a quarter of its 0.88 N
    assert fz.min_force_n(0.0, 12.0) == fz.FROZEN_FORCE_N
    assert fz.min_force_n(1.5, 12.0) == 1.5
