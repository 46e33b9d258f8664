"""The msgspec codec against the golden corpus written by the codec it replaced
(``golden/make_golden.py`` at the commit before the rewrite): identical wire bytes for every
message, identical decoded values, identical error codes and fields for every invalid packet,
except the verdicts issue 13 section 4 changed on purpose (listed in ``CHANGED``)."""
from __future__ import annotations

import importlib.util
import json
from enum import IntEnum
from pathlib import Path

import msgpack
import msgspec
import numpy as np
import pytest

from hapticproxy.protocol import codec as C
from hapticproxy.protocol.messages import MAX_ABS_FLOAT, PROTOCOL_MINOR
from hapticproxy.protocol.session import MacFramer

GOLDEN_DIR = Path(__file__).with_name("golden")
GOLDEN = json.loads((GOLDEN_DIR / "codec_golden.json").read_text(encoding="utf-8"))


def _load_generator():
    """The corpus's generator, for the way it turned a ContactUpdate's JSON arguments into arrays
    and an error into a verdict."""
    spec = importlib.util.spec_from_file_location("make_golden", GOLDEN_DIR / "make_golden.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_GENERATOR = _load_generator()
_call_cu, _error_verdict = _GENERATOR.call_cu, _GENERATOR.error_verdict

#: Verdicts changed on purpose (issue 13 section 4), with the new verdict's code and field.
CHANGED = {
    # an over-long string is BAD_SHAPE naming the field (and a Hello's nonce is read, so the
    # server can answer with Reject) instead of an unpacker failure
    "hello_28_engine": ("BAD_SHAPE", "engine"),
    # (this one is also short of fields: the field count is now checked before the strings)
    "error_long_str": ("MISSING_FIELD", "ref_type"),
    # a Hello with nonce 0 is refused (SPEC: random, non-zero)
    "hello_20_client_nonce": ("OUT_OF_RANGE", "client_nonce"),
    # a truncated Hello is still MALFORMED, but its nonce is read so it can be answered
    "truncated_hello": ("MALFORMED", ""),
}

#: Packets whose trailing values were unknown fields then and are fields of 1.2 now, with what
#: they decode to (the rest of the verdict unchanged).
APPENDED = {
    # ProxyState 1.2 appended epsilon_m: the old trailing 5 is now the advised epsilon
    "ps_trailing_ok": {"epsilon_m": 5.0, "unknown_fields": 0},
    # ContactUpdate 1.4 appended work_on_tool_j after tool_joint_position: the old trailing 7 is
    # now the engine's grant
    "cu_trailing_after_joints_ok": {"work_on_tool_j": 7.0, "unknown_fields": 0},
}


def _array(spec: dict) -> np.ndarray:
    return np.array(spec["data"], dtype=spec["dtype"]).reshape(spec["shape"])


def _plain(v):
    if isinstance(v, np.ndarray):
        return {"dtype": str(v.dtype), "shape": list(v.shape), "data": v.ravel().tolist()}
    if isinstance(v, IntEnum):
        return int(v)
    if isinstance(v, msgspec.Struct):
        return {f: _plain(getattr(v, f)) for f in v.__struct_fields__}
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    return v


def _build(cls_name: str, kwargs: dict):
    kw = dict(kwargs)
    for k in ("proxy_pose", "proxy_twist", "wrench", "joint_position", "joint_velocity", "joint_effort"):
        if k in kw:
            kw[k] = np.array(kw[k], dtype=np.float64)
    return getattr(C, cls_name)(**kw)


def _encode(codec, build: dict) -> bytes:
    if "message" in build:
        return codec.encode(_build(build["message"], build["kwargs"]))
    if "encode_contact_update" in build:
        return _call_cu(codec, build["encode_contact_update"])
    a = {k: (np.array(v, dtype=np.float64) if isinstance(v, list) else v) for k, v in build["encode_proxy_state"].items()}
    return codec.encode_proxy_state(**a)


def _verdict(codec, data: bytes) -> dict:
    out = codec.try_decode(data)
    if isinstance(out, C.ProtocolError):
        return _error_verdict(out)
    return {"ok": out}


def _same_decoded(msg, ref: dict) -> None:
    assert type(msg).__name__ == ref["type"]
    for name, want in ref["attrs"].items():
        got = getattr(msg, name)
        if isinstance(want, dict) and "dtype" in want:
            assert isinstance(got, np.ndarray), name
            assert got.dtype == np.dtype(want["dtype"]) and list(got.shape) == want["shape"], name
            np.testing.assert_array_equal(got, _array(want), err_msg=name)
        else:
            assert _plain(got) == want, name


@pytest.mark.parametrize("entry", GOLDEN["messages"], ids=lambda e: e["name"])
def test_every_message_encodes_to_the_same_bytes_and_decodes_to_the_same_values(entry):
    codec = C.Codec()
    packet = _encode(codec, entry["build"])
    old, new = msgpack.unpackb(bytes.fromhex(entry["hex"])), msgpack.unpackb(packet)
    # the header's minor is the writer's (informative): the corpus was written at 1.2; so were the
    # default version_max of a Hello and a Reject that did not name one
    assert (old[1], new[1]) == (2, PROTOCOL_MINOR)
    old[1] = new[1]
    kwargs = entry["build"].get("kwargs", entry["build"])
    vmax = {"Hello": 7, "Reject": 9}.get(entry["decoded"]["ok"]["type"])
    if vmax is not None and "version_max" not in kwargs:
        assert old[vmax] == [1, 2] and new[vmax] == [1, PROTOCOL_MINOR]
        old[vmax] = new[vmax]
    if entry["decoded"]["ok"]["type"] == "ProxyState":
        # 1.2 appended the engine's advice (issue 15): epsilon_m and lead_s, 0 (not advised) here;
        # 1.3 the device's inputs (issue 30): none reported here
        assert new[:len(old)] == old and new[len(old):] == [0.0, 0.0] + [0, 0.0, 0.0, 0]
    elif entry["build"].get("message") == "Welcome":
        # 1.2 appended the scene bounds, a note (issue 13 section 4) and the update watchdog
        # (issue 16): the old fields are unchanged, the new ones follow with their defaults
        assert new[:len(old)] == old
        assert new[len(old):] == [MAX_ABS_FLOAT] * 3 + ["", 0.0]
    else:
        assert new == old
    got = _verdict(codec, bytes.fromhex(entry["hex"]))
    assert "ok" in got, got
    _same_decoded(got["ok"], entry["decoded"]["ok"])


@pytest.mark.parametrize("entry", GOLDEN["packets"], ids=lambda e: e["name"])
def test_every_packet_gets_the_same_verdict(entry):
    codec = C.Codec(C.Limits(**entry["limits"])) if entry["limits"] else C.Codec()
    data = bytes.fromhex(entry["hex"])
    want = entry["verdict"]
    got = _verdict(codec, data)
    if entry["name"] in CHANGED:
        code, field = CHANGED[entry["name"]]
        assert (got.get("error"), got.get("field")) == (code, field), got
        assert got != want or entry["name"] == "truncated_hello"
        if entry["name"] in ("hello_28_engine", "truncated_hello"):
            assert got["client_nonce"] == 5 and got["type_id"] == 1  # answerable with Reject
        return
    if "ok" in want:
        assert "ok" in got, got
        if entry["name"] in APPENDED:
            want = {"ok": dict(want["ok"], attrs=dict(want["ok"]["attrs"], **APPENDED[entry["name"]]))}
        _same_decoded(got["ok"], want["ok"])
    else:
        assert got == want


def test_hmac_framing_is_unchanged():
    for e in GOLDEN["hmac"]:
        assert MacFramer(bytes.fromhex(e["key"])).seal(bytes.fromhex(e["packet"])).hex() == e["sealed"]


def test_the_corpus_covers_every_message_and_error_code_below_16():
    names = {e["decoded"]["ok"]["type"] for e in GOLDEN["messages"]}
    assert names == {c.__name__ for c in C.MESSAGE_CLASSES.values()}
    codes = {e["verdict"].get("error") for e in GOLDEN["packets"]}
    assert {c.name for c in C.ErrorCode if c < 15} <= codes
