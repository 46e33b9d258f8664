"""deploy/: every example config loads; every unit's and container's command line parses."""
import configparser
import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from hapticproxy.server import config as cfg

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "deploy" / "configs").glob("*.toml"))
HP = [sys.executable, "-m", "hapticproxy.cli.main"]


def test_there_are_examples():
    names = {p.name for p in CONFIGS}
    assert {"udp-loopback.toml", "zenoh-peer.toml", "zenoh-router-tls.toml"} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_example_config_loads(path):
    s = cfg.load(path)
    assert s.rate_hz > 0


def _serve_args(argv):
    """Map a deployed command line onto this checkout: same subcommand and options, with config
    paths under /etc/hapticproxy or /opt/hapticproxy replaced by this checkout's examples."""
    assert Path(argv[0]).name == "hapticproxy" and argv[1] == "serve", argv
    out = []
    for a in argv[2:]:
        if a.startswith("/etc/hapticproxy/server.toml"):
            a = str(ROOT / "deploy" / "configs" / "udp-loopback.toml")
        elif a.startswith("/opt/hapticproxy/"):
            a = str(ROOT / a[len("/opt/hapticproxy/"):])
        out.append(a)
    return out


def _check_command(argv):
    r = subprocess.run(HP + ["serve", *_serve_args(argv), "--print-config"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "[loop]" in r.stdout


def test_systemd_units_parse():
    units = sorted((ROOT / "deploy" / "systemd").glob("*.service"))
    assert units
    for unit in units:
        cp = configparser.ConfigParser(strict=True, interpolation=None)
        cp.read(unit)
        assert {"Unit", "Service", "Install"} <= set(cp.sections())
        _check_command(shlex.split(cp["Service"]["ExecStart"]))


def test_container_command_parses():
    text = (ROOT / "deploy" / "container" / "Containerfile").read_text()
    entry = json.loads(re.search(r"^ENTRYPOINT (\[.*\])$", text, re.M).group(1))
    cmd = json.loads(re.search(r"^CMD (\[.*\])$", text, re.M).group(1))
    _check_command(entry + cmd)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_example_config_prints_every_key_and_loads_back_the_same(path, tmp_path):
    s = cfg.load(path)
    text = s.to_toml()
    assert "[device]" in text and "\nmax_force_n = " in text.split("[device]")[1]
    f = tmp_path / path.name
    f.write_text(text)
    assert cfg.load(f).data == s.data
    fast = cfg.load(path, {"preset": "fast"})          # --preset wins over what the file pins
    assert fast.rate_hz == 512.0 and fast["model"]["capacity"] == 16
