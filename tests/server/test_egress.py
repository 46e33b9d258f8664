"""The server's ProxyState kernel (``server/egress.py``) packs the bytes the codec packs: for
random states (every integer width, tokens using all 64 bits, joint arrays of every length,
both layouts: minor 1 without and minor 2 with the engine's advice), at the float bound, and
it leaves what breaks a rule (not finite, beyond the bound) to the codec, which refuses it
as it does without the kernel."""
from __future__ import annotations

import numpy as np
import pytest

from hapticproxy.protocol.codec import Codec
from hapticproxy.protocol.messages import MAX_ABS_FLOAT, ProxyState
from hapticproxy.server import egress


def _pose(rng):
    p = rng.normal(size=7)
    p[3:] /= np.linalg.norm(p[3:])
    return p


def _state(rng, joints: int):
    width = rng.choice([1, 100, 300, 70_000, 5_000_000_000, (1 << 63) - 1])
    token = int(rng.integers(0, 1 << 63)) * 2 + int(rng.integers(0, 2))  # all 64 bits
    return dict(session_id=int(rng.integers(0, 1 << 32)), token=token,
                seq=int(rng.integers(1, width, endpoint=True)), ack_seq=int(rng.integers(0, width, endpoint=True)),
                server_time_s=float(rng.uniform(0, 1e4)), proxy_pose=_pose(rng), proxy_twist=rng.normal(size=6),
                wrench=rng.normal(size=6), joint_position=rng.normal(size=joints),
                joint_velocity=rng.normal(size=joints), joint_effort=rng.normal(size=joints),
                server_state=int(rng.integers(0, 5)), epsilon_m=float(rng.uniform(0, 0.01)),
                lead_s=float(rng.uniform(0, 0.05)))


def _pack(codec, s):
    return codec.encode_proxy_state(s["session_id"], s["token"], s["seq"], s["ack_seq"], s["server_time_s"],
                                    s["proxy_pose"], s["proxy_twist"], s["wrench"], s["joint_position"],
                                    s["joint_velocity"], s["joint_effort"], s["server_state"],
                                    epsilon_m=s["epsilon_m"], lead_s=s["lead_s"], trusted=True)


@pytest.mark.parametrize("minor", [1, 2])
def test_the_kernel_packs_the_codecs_bytes(minor):
    plain = Codec(minor=minor)
    calls = []
    packer = egress.ProxyStatePacker(32)

    def spy(*a):
        calls.append(packer(*a))
        return calls[-1]

    fast = Codec(minor=minor, proxy_state_packer=spy)
    rng = np.random.default_rng(minor)
    for trial in range(400):
        s = _state(rng, int(rng.integers(0, 32)))
        if trial % 10 == 0:
            s["proxy_twist"][int(rng.integers(0, 6))] = rng.choice([-1.0, 1.0]) * MAX_ABS_FLOAT  # at the bound
        a, b = _pack(plain, s), _pack(fast, s)
        assert a == b, trial
        assert calls[-1] is not None  # the kernel packed it
        msg = plain.decode(b)
        assert isinstance(msg, ProxyState) and msg.seq == s["seq"] and msg.token == s["token"]
    assert plain.counters.encoded == fast.counters.encoded == 400


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, MAX_ABS_FLOAT * 2])
@pytest.mark.parametrize("where", ["proxy_pose", "wrench", "joint_effort", "server_time_s", "lead_s"])
def test_what_breaks_a_rule_is_left_to_the_codec(bad, where):
    packer = egress.ProxyStatePacker(32)
    fast = Codec(minor=2, proxy_state_packer=packer)
    plain = Codec(minor=2)
    s = _state(np.random.default_rng(7), 3)
    if isinstance(s[where], np.ndarray):
        s[where][1] = bad
    else:
        s[where] = bad
    outcomes = []
    for codec in (plain, fast):
        try:
            outcomes.append(_pack(codec, s))
        except ValueError as exc:
            outcomes.append(str(exc))
    assert outcomes[0] == outcomes[1]
    if where != "lead_s":  # (the trusted path takes the advice as the kernel computed it)
        assert isinstance(outcomes[0], str), outcomes[0]  # refused, with the codec's words
