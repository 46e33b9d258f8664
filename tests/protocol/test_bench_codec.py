"""``hapticproxy bench codec --json`` runs and prints the promised rows and keys. Figures are
not judged here at all (no wall-clock thresholds or timing ratios: issue 14 item 9); the
benchmark is the command that prints them."""
from __future__ import annotations

import json

from hapticproxy.benchmarks import bench_codec
from hapticproxy.cli.main import main as cli_main

KEYS = {"message", "contacts", "encode_median_us", "decode_median_us", "bytes", "naive_encode_median_us",
        "naive_decode_median_us", "encode_speedup", "decode_speedup"}


def test_bench_codec_json_rows(capsys):
    assert cli_main(["bench", "codec", "--json", "--batch", "20", "--repeats", "5"]) == 0
    rows = json.loads(capsys.readouterr().out)
    cu = [r for r in rows if r["message"] == "ContactUpdate"]
    assert [r["contacts"] for r in cu] == [0, 8, 32, 64]
    for r in rows:
        assert KEYS <= set(r)
        assert all(r[k] > 0 for k in KEYS - {"message", "contacts"})
    # Packed layout: 88 bytes per contact plus a fixed envelope.
    # (bins over 255 bytes take a 2-byte length instead of 1, hence the tolerance)
    assert all(abs(r["bytes"] - cu[0]["bytes"] - 88 * r["contacts"]) <= 2 for r in cu)
    assert [r["message"] for r in rows] == ["ContactUpdate"] * 4 + ["ProxyState"]


def test_naive_codec_decodes_what_it_encodes():
    keys, pos, nor, sep, vc = bench_codec.make_contacts(5)
    out = bench_codec.naive_decode_contacts(bench_codec.naive_encode_contacts(1, 0.0, bench_codec.POSE, keys, pos, nor, sep, vc))
    assert (out[0] == keys).all() and (out[1] == pos).all() and (out[2] == nor).all()


def test_table_output(capsys):
    assert bench_codec.main(["--batch", "5", "--repeats", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["message", "contacts", "bytes", "encode_median_us", "decode_median_us",
                                "server_decode_median_us", "naive_encode_median_us", "naive_decode_median_us",
                                "encode_speedup", "decode_speedup"]
    assert [ln.split()[0] for ln in lines[1:]] == ["ContactUpdate"] * 4 + ["ProxyState"]
