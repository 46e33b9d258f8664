"""Property-based fuzzing of the decoder: it never raises, and whatever it accepts is valid.

Default run: 12,600 cases (random bytes 10,000 -- the issue's floor on its own -- plus 1,000
mutated real packets, 800 msgpack-shaped garbage, 800 poisoned contact values), 500 cases
whose accepted ContactUpdates are applied to a local model, and a 5,000-input smoke of the long
run's generator. Opt-in (``-m slow``): the same four properties with 1,000,000 cases in all, and
the long run itself (``python -m hapticproxy.benchmarks.fuzz_codec``, 1,000,000 inputs).
"""
from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hapticproxy.protocol import messages as M
from hapticproxy.protocol.codec import Codec, ContactUpdate, Limits, Message, ProtocolError

LIMITS = Limits(max_contacts=16, max_packet_bytes=4096)
CODEC = Codec(LIMITS)
RNG = np.random.default_rng(1)


def _valid_packet(n: int, seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    keys = np.column_stack([np.zeros(n, np.int64), rng.integers(0, 3, n), np.arange(n)]).astype(np.int64)
    nor = rng.normal(size=(n, 3))
    nor /= np.linalg.norm(nor, axis=1)[:, None]
    return CODEC.encode_contact_update(1, 2, 1 + seed, 0.5, (0, 0, 0, 1, 0, 0, 0), keys, rng.normal(size=(n, 3)),
                                       nor, rng.normal(size=n), rng.normal(size=n))


SEEDS = [_valid_packet(n, n) for n in (0, 1, 3, 16)]


def assert_valid(msg: Message) -> None:
    """What the local model relies on, re-checked independently of the decoder."""
    if isinstance(msg, ContactUpdate):
        n = msg.keys.shape[0]
        assert 0 <= n <= LIMITS.max_contacts
        assert msg.keys.dtype == np.int64 and msg.keys.shape == (n, 3)
        for a, shape in ((msg.position_m, (n, 3)), (msg.normal, (n, 3)), (msg.separation_m, (n,)),
                         (msg.v_constr_m_per_s, (n,)), (msg.tool_pose, (7,))):
            assert a.dtype == np.float64 and a.shape == shape
            assert np.all(np.isfinite(a)) and np.all(np.abs(a) <= M.MAX_ABS_FLOAT)
        if n:
            assert np.all(np.abs(np.linalg.norm(msg.normal, axis=1) - 1) <= M.UNIT_TOLERANCE * 1.0000001)
        assert abs(np.linalg.norm(msg.tool_pose[3:]) - 1) <= M.UNIT_TOLERANCE * 1.0000001
        assert len({tuple(k) for k in msg.keys.tolist()}) == n
        assert isinstance(msg.seq, int) and msg.seq >= 1 and math.isfinite(msg.env_time_s)


def check(data: bytes) -> None:
    out = CODEC.try_decode(data)  # must never raise
    if isinstance(out, ProtocolError):
        assert isinstance(out.code, M.ErrorCode)
        # The catch-all in try_decode is a last line of defence, not a classifier: reaching it
        # means a validator crashed on some input.
        assert not out.detail.startswith("unexpected"), out
    else:
        assert isinstance(out, Message)
        assert_valid(out)


@settings(max_examples=10_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.binary(max_size=256))
def test_random_bytes_never_raise(data):
    check(data)


def _mutations():
    seed = st.sampled_from(SEEDS)
    flip = st.tuples(seed, st.integers(0, 10_000), st.integers(0, 255)).map(
        lambda t: t[0][: t[1] % len(t[0])] + bytes([t[2]]) + t[0][t[1] % len(t[0]) + 1:])
    cut = st.tuples(seed, st.integers(0, 10_000)).map(lambda t: t[0][: t[1] % len(t[0])])
    splice = st.tuples(seed, st.integers(0, 10_000), st.binary(max_size=16)).map(
        lambda t: t[0][: t[1] % len(t[0])] + t[2] + t[0][t[1] % len(t[0]):])
    return st.one_of(flip, cut, splice)


@settings(max_examples=1_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(_mutations())
def test_mutated_real_packets_never_raise_and_accepted_ones_are_valid(data):
    check(data)


# msgpack-shaped garbage: header-like prefixes followed by arbitrary msgpack values.
_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(2 ** 63), 2 ** 64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8), st.binary(max_size=80),
)
_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=6), max_leaves=20)
_float_bins = st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=40).map(
    lambda xs: np.asarray(xs, "<f8").tobytes())


STRUCTURED = st.tuples(
    st.sampled_from([int(m.type_id) for m in M.MESSAGES] + [0, 99]),
    st.sampled_from([1, 1, 1, 2]),
    st.lists(st.one_of(_values, _float_bins, st.integers(0, 20)), max_size=16),
).map(lambda t: msgpack.packb([t[1], 0, t[0], 1, 1] + t[2], use_bin_type=True))


@settings(max_examples=800, deadline=None, suppress_health_check=list(HealthCheck))
@given(STRUCTURED)
def test_structured_garbage_never_raises(data):
    check(data)


def _poisoned(n: int, poison: list, where: int) -> bytes:
    obj = msgpack.unpackb(_valid_packet(n, 5))
    data = np.frombuffer(obj[10], "<f8").copy()
    pose = np.frombuffer(obj[7], "<f8").copy()
    for i, x in enumerate(poison):
        if data.size and i % 2 == 0:
            data[(where + i * 7) % data.size] = x
        else:
            pose[(where + i) % 7] = x
    obj[10], obj[7] = data.tobytes(), pose.tobytes()
    return msgpack.packb(obj, use_bin_type=True)


POISONED = st.tuples(st.integers(0, 16),
                     st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=1, max_size=8),
                     st.integers(0, 10_000)).map(lambda t: _poisoned(*t))


@settings(max_examples=800, deadline=None, suppress_health_check=list(HealthCheck))
@given(POISONED)
def test_poisoned_contact_values_are_rejected_or_valid(data):
    check(data)


# ------------------------------------------------------------------ what reaches the model
_PROBE = None


def _probe():
    global _PROBE
    if _PROBE is None:
        from hapticproxy.benchmarks.fuzz_codec import ModelProbe

        _PROBE = ModelProbe()
    return _PROBE


@settings(max_examples=500, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.one_of(_mutations(), POISONED))
def test_accepted_updates_keep_a_local_model_finite(data):
    """Whatever the decoder accepts, applied to a local model (update + one step from a fresh
    state), leaves it finite."""
    out = CODEC.try_decode(data)
    if isinstance(out, ContactUpdate):
        assert not _probe().nonfinite(out)


def test_the_long_runs_generator_finds_nothing_in_a_short_run():
    from hapticproxy.benchmarks.fuzz_codec import run_chunk

    r = run_chunk(seed=3, n=5_000, quiet_gc=False)
    assert r["inputs"] == 5_000
    assert not r["unhandled"] and not r["catch_all"] and not r["invalid"] and r["model_nonfinite"] == 0
    assert sum(r["accepted"].values()) > 100 and len(r["rejected"]) >= 8  # it reaches deep and wide


# ------------------------------------------------------------------ the long runs (opt-in)
def _long(strategy, n: int):
    return settings(max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck))(
        given(strategy)(check))


@pytest.mark.slow
@pytest.mark.parametrize("name, strategy, n", [
    ("random bytes", st.binary(max_size=256), 600_000),
    ("mutated packets", _mutations(), 250_000),
    ("poisoned values", POISONED, 100_000),
    ("structured garbage", STRUCTURED, 50_000),
])
def test_long_hypothesis_run_one_million_cases_in_all(name, strategy, n):
    _long(strategy, n)()


@pytest.mark.slow
def test_long_run_one_million_inputs():
    from hapticproxy.benchmarks.fuzz_codec import run_random

    st_, crashes = run_random(1_000_000, seed=1, jobs=2)
    assert st_.inputs == 1_000_000 and not crashes
    assert not st_.unhandled and not st_.catch_all and not st_.invalid and st_.model_nonfinite == 0
