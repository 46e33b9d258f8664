"""The remote-device link's declaration (protocol/devlink.py) reproduces the bytes of the
hand-written packers it replaced (golden/devlink_golden.json, written by
golden/make_devlink_golden.py from the old code), field by field and as a recorded exchange
between a device program and a server driver replayed byte for byte: the golden STATEs are the
layout's version 1 (216 bytes), which a device without inputs still sends and every server
takes; version 2 appends the device's inputs to the row."""
from __future__ import annotations

import importlib.util
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from hapticproxy.protocol import devlink as dl
from hapticproxy.protocol.devlink import COMMAND, STATE, STATE_V1

GOLDEN_DIR = Path(__file__).with_name("golden")
GOLDEN = json.loads((GOLDEN_DIR / "devlink_golden.json").read_text(encoding="utf-8"))


#: Each golden set: its datagram, the JSON key of its one flag and that flag's bit, its float64 array.
_SETS = {"state": (STATE_V1, "armed", dl.F_ARMED, "state"), "command": (COMMAND, "enable", dl.F_ENABLE, "wrench")}


def _values(kind: str, f: dict) -> dict:
    """A golden case's fields as ``pack`` takes them (the flag as its bit in ``flags``)."""
    _, flag_key, bit, _ = _SETS[kind]
    f = dict(f)
    f["flags"] = bit if f.pop(flag_key) else 0
    return f


def test_the_declared_layouts_are_the_hand_written_ones():
    # the struct strings server/devices/remote.py used before the declaration
    assert STATE.header.format == STATE_V1.header.format == "<4sBBHQQIIQQBB6x" and STATE.header.size == 56
    assert COMMAND.header.format == "<4sBBHQQIIQQ" and COMMAND.header.size == 48
    assert (STATE_V1.size, COMMAND.size) == (GOLDEN["state_size"], GOLDEN["command_size"]) == (216, 96)
    assert STATE.offsets["state"] == STATE_V1.offsets["state"] == 56 and COMMAND.offsets["wrench"] == 48
    # version 2: the row's inputs appended (3 floats), the rest where it was
    assert (STATE.size, STATE.version, STATE_V1.version, COMMAND.version) == (216 + 24, 2, 1, 1)
    assert COMMAND.offsets["engagements"] == 28 and STATE.offsets["kind"] == 48


@pytest.mark.parametrize(("kind", "i"), [(kind, i) for kind in _SETS for i in range(len(GOLDEN[kind]))])
def test_datagram_bytes_match_the_golden_set(kind, i):
    datagram, _, _, array_field = _SETS[kind]
    case = GOLDEN[kind][i]
    values = _values(kind, case["fields"])
    data = datagram.pack(**values)
    assert data.hex() == case["hex"]
    back = datagram.unpack(data)
    for k, v in values.items():
        if k == array_field:
            np.testing.assert_array_equal(getattr(back, k), np.array(v))
        else:
            assert getattr(back, k) == v, k


def test_a_recorded_exchange_replays_byte_for_byte():
    """The device program and the server driver (now on the declaration and the Transport
    interface) send exactly the datagrams the old code sent in the same simulated-time script."""
    spec = importlib.util.spec_from_file_location("make_devlink_golden", GOLDEN_DIR / "make_devlink_golden.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    got = mod._session()
    want = GOLDEN["session"]
    assert [g["dir"] for g in got] == [w["dir"] for w in want]
    for n, (g, w) in enumerate(zip(got, want)):
        assert g["hex"] == w["hex"], f"datagram {n} ({w['dir']}) differs"


def test_unpack_and_pack_refuse_what_is_not_a_datagram():
    good = COMMAND.pack(flags=1, device_session=1, server_session=2, epoch=1, engagements=0, seq=1, state_seq=0,
                        wrench=[0.0] * 6)
    with pytest.raises(ValueError, match="expected 96 bytes"):
        COMMAND.unpack(good[:-1])
    with pytest.raises(ValueError, match="bad prefix"):
        COMMAND.unpack(b"XXXX" + good[4:])
    with pytest.raises(ValueError, match="bad prefix"):
        STATE.unpack(good + bytes(STATE.size - COMMAND.size))   # right size, COMMAND's type byte
    v1 = STATE_V1.pack(flags=0, device_session=1, server_session=0, epoch=0, period_us=1000, seq=1, cmd_seq=0, kind=1,
                       fault=0, state=[0.0] * dl.ROW_FLOATS_V1)
    with pytest.raises(ValueError, match="bad prefix"):
        STATE.unpack(v1 + bytes(STATE.size - STATE_V1.size))   # version 2's size, version 1's version byte
    with pytest.raises(ValueError, match="bad prefix"):
        STATE_V1.unpack(v1[:4] + bytes([2]) + v1[5:])           # version 1's size, version 2's byte

    with pytest.raises(ValueError, match="missing fields \\['engagements'\\]"):
        COMMAND.pack(flags=1, device_session=1, server_session=2, epoch=1, seq=1, state_seq=0, wrench=[0.0] * 6)
    with pytest.raises(ValueError, match="COMMAND"):
        COMMAND.pack(flags=1, device_session=-1, server_session=2, epoch=1, engagements=0, seq=1, state_seq=0,
                     wrench=[0.0] * 6)
    with pytest.raises(ValueError, match="wrench: expected 6 floats"):
        COMMAND.pack(flags=1, device_session=1, server_session=2, epoch=1, engagements=0, seq=1, state_seq=0,
                     wrench=[0.0] * 5)


def test_the_hot_path_buffers_carry_the_prefix_and_a_view_of_the_block():
    buf = STATE.new_buffer()
    assert struct.unpack_from("<4sBB", buf) == (dl.MAGIC, dl.VERSION, dl.DatagramType.STATE) == \
        (dl.MAGIC, STATE.version, dl.DatagramType.STATE)
    view = STATE.floats(buf)
    view[:] = np.arange(dl.ROW_FLOATS)
    STATE.body.pack_into(buf, dl.PREFIX_BYTES, 1, 7, 8, 9, 1000, 3, 2, 1, 0)
    back = STATE.unpack(bytes(buf))
    assert (back.flags, back.device_session, back.seq, back.kind) == (1, 7, 3, 1)
    np.testing.assert_array_equal(back.state, np.arange(dl.ROW_FLOATS))


def test_the_drivers_numbers_are_the_links():
    from hapticproxy.server.devices import base
    from hapticproxy.server.devices.layout import KIND_IDS

    assert {n: int(k) for k, n in dl.KIND_NAMES.items()} == KIND_IDS
    assert {int(f) for f in dl.DeviceFault} == set(base.DEV_FAULT_NAMES)
    assert (base.DS_POSE, base.DS_TWIST, base.DS_HAND, base.DS_TIME, base.DS_BUTTONS, base.DS_GRIPPER,
            base.DEV_NSTATE) == tuple(c.start for c in dl.ROW_COLUMNS) + (dl.ROW_FLOATS,)
    # the appended columns keep the earlier ones' numbers (version 1's row is the first 20)
    assert (base.DS_TIME, base.DS_BUTTONS, dl.ROW_FLOATS_V1) == (19, 20, 20)


def test_spec_appendix_is_generated_from_the_declaration():
    from hapticproxy.protocol import spec
    from hapticproxy.protocol.device_conformance import DEVICE_RULES, SERVER_RULES

    text = spec.SPEC_PATH.read_text(encoding="utf-8")
    block = spec.extract_block(text, "devlink")
    assert block == spec.render_block("devlink")
    assert text.index("## Appendix A. The remote-device link") < text.index(block)
    for d in dl.DATAGRAMS:
        assert f"#### {d.name} (type {int(d.type_id)}, {d.direction}, {d.size} bytes)" in block
        for f in d.fields:
            if not f.padding:
                assert f"| {d.offsets[f.name]} | {f.size} | {f.wire} | `{f.name}` |" in block
    for rule in list(DEVICE_RULES) + list(SERVER_RULES):
        assert f"| `{rule}` |" in block
    dump = block[block.index("```text", block.index("The 96 bytes:")) + 7:]
    data = bytes.fromhex("".join(line[6:] for line in dump[:dump.index("```")].strip().splitlines()))
    c = COMMAND.unpack(data)
    e = spec.DEVLINK_EXAMPLE
    assert (c.flags, c.device_session, c.server_session, c.epoch, c.engagements, c.seq, c.state_seq) == \
        (e["flags"], e["device_session"], e["server_session"], e["epoch"], e["engagements"], e["seq"], e["state_seq"])
    np.testing.assert_array_equal(c.wrench, e["wrench"])
