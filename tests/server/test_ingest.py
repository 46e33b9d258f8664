"""The server's kernels that vouch for an arriving ContactUpdate (server/ingest.py) change what it
costs to receive one, never what is accepted: a codec and a session with the kernels plugged in
give the same verdict (the same arrays, or the same error code, field and detail) as without
them, on valid updates and on each way an update can break a rule, at the edges of the rules."""
import numpy as np
import pytest
from server_harness import break_contact_rule, random_contacts as _contacts

from hapticproxy.protocol.codec import Codec, Limits, ProtocolError
from hapticproxy.protocol.messages import UNIT_TOLERANCE
from hapticproxy.server import ingest

POSE = np.array([0.0, 0.05, 0.0, 1.0, 0.0, 0.0, 0.0])


def _broken(rng, n):
    """A batch of updates, each valid or breaking one codec rule (some at its edge)."""
    out = []
    for case in ("valid", "nan", "inf", "big", "at_max", "not_unit", "unit_edge_in", "unit_edge_out",
                 "duplicate", "many_unique", "many_duplicate", "zero"):
        m = 80 if case.startswith("many") else (0 if case == "zero" else n)
        keys, pos, normal, sep, vc = _contacts(rng, m)
        break_contact_rule(case, rng, int(rng.integers(0, max(m, 1))), keys, pos, normal, sep, vc)
        out.append((case, keys, pos, normal, sep, vc))
    return out


def _verdict(codec, packet):
    try:
        msg = codec.decode(packet)
    except ProtocolError as exc:
        return ("refused", exc.code, exc.field, exc.detail)
    return ("accepted", msg.keys.tobytes(), msg.position_m.tobytes(), msg.normal.tobytes(),
            msg.separation_m.tobytes(), msg.v_constr_m_per_s.tobytes())


def test_the_codec_accepts_and_refuses_the_same_updates_with_the_kernel():
    lim = Limits(max_contacts=128)  # above the kernel's pairwise key comparison (64)
    plain = Codec(lim)
    fast = Codec(lim, contact_check=ingest.contacts_surely_valid)
    rng = np.random.default_rng(3)
    accepted = {"valid", "at_max", "unit_edge_in", "many_unique", "zero"}
    for trial in range(40):
        for case, keys, pos, normal, sep, vc in _broken(rng, int(rng.integers(2, 20))):
            pkt = plain.encode_contact_update(1, 2, trial + 1, 0.5, POSE, keys, pos, normal, sep, vc)
            a, b = _verdict(plain, pkt), _verdict(fast, pkt)
            assert a == b, case
            # the case does what it says (so the comparison covered each rule)
            assert a[0] == ("accepted" if case in accepted else "refused"), (case, a)


def test_the_kernel_vouches_only_for_what_it_is_sure_of():
    rng = np.random.default_rng(4)
    keys, pos, normal, sep, vc = _contacts(rng, 6)
    codec = Codec()
    calls = []

    def spy(cols, normal_, keys_):
        calls.append(ingest.contacts_surely_valid(cols, normal_, keys_))
        return calls[-1]

    spying = Codec(contact_check=spy)
    for scale in (1.0, 1.0 + UNIT_TOLERANCE * (1 - 1e-9)):
        nn = normal.copy()
        nn[0] *= scale
        spying.decode(codec.encode_contact_update(1, 2, 1, 0.5, POSE, keys, pos, nn, sep, vc))
    # a plain update is vouched for; a normal a hair inside the tolerance is left to the codec's
    # numpy rules (rounding could tell the two apart there), which accept it
    assert calls == [True, False]


def _session(planar: bool, n_links: int = 1):
    """A ServerSession-like object: the bounds check reads only these attributes."""
    from types import SimpleNamespace

    from hapticproxy.protocol.session import ServerSession

    s = SimpleNamespace(bounds=(0.5, 2.0, 0.05), n_joints=0, n_links=n_links, planar=planar, update_check=None)
    return s, ServerSession.check_update


@pytest.mark.parametrize("planar", [False, True])
def test_session_check_is_the_same_with_the_bounds_kernel(planar):
    codec = Codec()
    rng = np.random.default_rng(5 + planar)
    s, check = _session(planar, n_links=2)
    verdicts = set()
    for trial in range(300):
        n = int(rng.integers(1, 12))
        keys, pos, normal, sep, vc = _contacts(rng, n, planar)
        i = int(rng.integers(0, n))
        case = trial % 8
        if case == 1:
            pos[i, int(rng.integers(0, 3))] = rng.choice([-1, 1]) * 0.5 * (1 + rng.choice([0.0, 1e-12]))
        elif case == 2:
            vc[i] = rng.choice([-1, 1]) * 2.0 * (1 + rng.choice([0.0, 1e-12]))
        elif case == 3:
            sep[i] = rng.choice([-1, 1]) * 0.05 * (1 + rng.choice([0.0, 1e-12]))
        elif case == 4:
            keys[i, 0] = rng.choice([-1, 1, 2])
        elif case == 5:
            normal[i] = [np.sqrt(1 - 4e-12), 0.0, rng.choice([2e-6, 1e-6, 5e-7])]
        msg = codec.decode(codec.encode_contact_update(1, 2, 1, 0.5, POSE, keys, pos, normal, sep, vc))
        s.update_check = None
        a = check(s, msg)
        s.update_check = ingest.update_surely_in_bounds
        b = check(s, msg)
        assert a == b, (case, a, b)
        verdicts.add(None if a is None else a[0])
    expected = {None, "oob_workspace", "oob_speed", "oob_separation", "unusable_tool_link"}
    assert expected <= verdicts
    assert ("unusable_normal_z" in verdicts) == planar
