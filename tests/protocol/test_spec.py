"""SPEC.md's generated blocks match the declarations; its worked example decodes."""
from __future__ import annotations

import re
import subprocess
import sys

import numpy as np

from hapticproxy.protocol import messages as M
from hapticproxy.protocol import spec
from hapticproxy.protocol.codec import Codec


def test_spec_contains_exactly_the_rendered_blocks():
    text = spec.SPEC_PATH.read_text(encoding="utf-8")
    for name in spec.BLOCKS:
        assert spec.extract_block(text, name) == spec.render_block(name), (
            f"SPEC.md block {name!r} is stale: run python -m hapticproxy.protocol.spec --write")


def test_every_declared_field_and_wire_type_is_documented():
    text = spec.SPEC_PATH.read_text(encoding="utf-8")
    wire_types_section = text[text.index("### Wire types"):text.index("### Packed contact arrays")]
    for m in M.MESSAGES:
        assert f"### {m.name} (type_id {int(m.type_id)}" in text
        for f in m.fields + M.LINK_FIELDS + M.HEADER:
            assert f"`{f.name}`" in text
            generic = re.sub(r"\[\d+\]$", "[k]", f.type)
            generic = re.sub(r"^bin f64\[\d+\]$", "bin f64[k]", generic)
            assert f"`{generic}`" in wire_types_section or generic in ("u16", "u32", "u64", "u8"), f.type


def test_worked_example_hex_decodes_to_the_stated_values():
    text = spec.SPEC_PATH.read_text(encoding="utf-8")
    block = spec.extract_block(text, "example")
    dump = block[block.index("```text", block.index("bytes:")) + 7:]
    dump = dump[:dump.index("```")]
    data = bytes.fromhex("".join(line[6:] for line in dump.strip().splitlines()))
    msg = Codec().decode(data)
    e = spec.EXAMPLE
    assert (msg.session_id, msg.token, msg.seq, msg.env_time_s) == (e["session_id"], e["token"], e["seq"], e["env_time_s"])
    np.testing.assert_array_equal(msg.keys, e["keys"])
    np.testing.assert_array_equal(msg.position_m, e["position_m"])
    np.testing.assert_array_equal(msg.normal, e["normal"])
    np.testing.assert_array_equal(msg.separation_m, e["separation_m"])
    np.testing.assert_array_equal(msg.v_constr_m_per_s, e["v_constr_m_per_s"])
    np.testing.assert_array_equal(msg.tool_pose, e["tool_pose"])


def test_check_flag_detects_staleness(tmp_path, monkeypatch):
    real = spec.SPEC_PATH.read_text(encoding="utf-8")
    stale = real.replace("| 4 | `ContactUpdate` |", "| 4 | `ContactUpdat` |")
    assert stale != real
    target = tmp_path / "SPEC.md"
    target.write_text(stale, encoding="utf-8")
    monkeypatch.setattr(spec, "SPEC_PATH", target)
    assert spec.main(["--check"]) == 1
    assert spec.main(["--write"]) == 0
    assert spec.main(["--check"]) == 0
    assert target.read_text(encoding="utf-8") == real


def test_module_entry_point_checks_the_real_file():
    out = subprocess.run([sys.executable, "-m", "hapticproxy.protocol.spec", "--check"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_spec_names_the_zenoh_key_expressions_the_code_uses():
    from hapticproxy.protocol.transport import zenoh_backend as zb
    text = spec.SPEC_PATH.read_text(encoding="utf-8")
    assert f"`{zb.c2s_key('SESSION', 'CLIENT')}`" in text
    assert f"`{zb.s2c_key('SESSION', 'CLIENT')}`" in text
    assert f"{zb.KEY_PREFIX}/SESSION/c2s/*" in text
