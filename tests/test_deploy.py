"""deploy/: every example config loads; every unit's and container's command line parses."""
import configparser
import json
import re
import shlex
import shutil
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


def _unit_for_this_checkout(tmp_path) -> Path:
    """The unit with its commands pointing at this checkout's installed command (verify checks
    that every command exists and is executable)."""
    unit = (ROOT / "deploy" / "systemd" / "hapticproxy.service").read_text()
    exe = Path(sys.executable).parent / "hapticproxy"
    out = tmp_path / "hapticproxy.service"
    out.write_text(unit.replace("/opt/hapticproxy/.venv/bin/hapticproxy", str(exe)))
    return out


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_unit_verifies(tmp_path):
    r = subprocess.run(["systemd-analyze", "verify", str(_unit_for_this_checkout(tmp_path))], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0 and r.stderr.strip() == "", r.stderr  # unknown keys are only warned about


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None, reason="systemd-sysusers not installed")
def test_sysusers_creates_the_service_user():
    path = ROOT / "deploy" / "systemd" / "hapticproxy.sysusers"
    r = subprocess.run(["systemd-sysusers", "--dry-run", str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "Creating user 'hapticproxy'" in r.stdout + r.stderr


def test_systemd_unit_never_cold_starts_and_keeps_real_time():
    cp = configparser.ConfigParser(strict=True, interpolation=None)
    cp.read(ROOT / "deploy" / "systemd" / "hapticproxy.service")
    svc = cp["Service"]
    assert svc["User"] == "hapticproxy" and svc["CacheDirectory"] == "hapticproxy"
    assert "NUMBA_CACHE_DIR=/var/cache/hapticproxy/" in svc["Environment"]
    assert shlex.split(svc["ExecStartPre"])[1:] == ["warmup", "--quiet"]
    # hardening options a real-time, JIT-compiled process cannot take
    assert "RestrictRealtime" not in svc and "MemoryDenyWriteExecute" not in svc
    assert svc["AmbientCapabilities"] == "CAP_SYS_NICE"


def test_container_is_built_warm_and_runs_as_its_own_user():
    text = (ROOT / "deploy" / "container" / "Containerfile").read_text()
    lines = [ln for ln in text.splitlines() if ln and not ln.startswith("#")]
    assert not any(ln.startswith("EXPOSE") for ln in lines)  # the default config binds 127.0.0.1
    assert any(ln.startswith("ENV NUMBA_CACHE_DIR=") for ln in lines)
    build = "\n".join(ln for ln in lines if ln.startswith(("RUN", " &&")))
    assert "hapticproxy warmup" in build and "chown -R hapticproxy" in build
    users = [ln.split()[1] for ln in lines if ln.startswith("USER ")]
    assert users and users[-1] == "hapticproxy"
    health = next(ln for ln in lines if ln.startswith("HEALTHCHECK"))
    assert "status" in health or "status" in text[text.index("HEALTHCHECK"):].split("\n", 2)[1]
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert {".venv", "out", "**/__pycache__", "**/*.nbi", "**/*.nbc"} <= set(ignored)


@pytest.mark.slow
def test_the_units_warm_up_fills_its_cache_and_the_server_then_compiles_nothing(tmp_path):
    """What the systemd unit does (and the container build): `hapticproxy warmup` with the
    service's NUMBA_CACHE_DIR, then `serve`: the loop process loads every kernel from that cache
    and says nothing about compiling. Slow (a full compile, ~90 s on 2 cores): ``.ci/run`` runs
    the same sequence with an empty NUMBA_CACHE_DIR on every CI run."""
    import os

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    w = subprocess.run(HP + ["warmup"], capture_output=True, text=True, timeout=900, env=env)
    assert w.returncode == 0, w.stderr
    assert "compiling" in w.stderr                              # the cache was empty
    again = subprocess.run(HP + ["warmup"], capture_output=True, text=True, timeout=300, env=env)
    assert "(0 compiled now" in again.stderr and "compiling" not in again.stderr
    port = _free_udp_port()
    s = subprocess.run(HP + ["serve", "--url", f"udp://127.0.0.1:{_free_udp_port()}", "--status",
                             f"127.0.0.1:{port}", "--duration", "0.5"], capture_output=True, text=True,
                       timeout=300, env=env)
    assert s.returncode == 0, s.stderr
    assert "compiling" not in s.stderr


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sk:
        sk.bind(("127.0.0.1", 0))
        return sk.getsockname()[1]


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


def _pins(path: Path) -> dict:
    return {ln.split("==")[0].lower(): ln.split("==")[1].strip() for ln in path.read_text().splitlines()
            if "==" in ln and not ln.startswith("#")}


def test_the_server_only_lock_is_the_servers_part_of_the_full_one():
    """Issue 32, papercut 16: a server image installs the server, not every extra. The server lock
    pins the same versions as requirements.lock, holds every core dependency of pyproject.toml
    (and Zenoh, which the shipped configs use), and none of the engines, GUI, plots, viewer or
    test tools; the container and the systemd unit's instructions install it."""
    import tomllib

    full, server = _pins(ROOT / "requirements.lock"), _pins(ROOT / "requirements-server.lock")
    assert all(full.get(k) == v for k, v in server.items()), {k: (v, full.get(k)) for k, v in server.items()}
    core = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    for dep in core + ["eclipse-zenoh"]:
        name = re.split(r"[<>=!~ \[]", dep, maxsplit=1)[0].lower()
        assert name in server, f"{name} (a core dependency) is not in requirements-server.lock"
    for extra in ("pybullet", "pymunk", "pygame", "matplotlib", "pylint", "box2d", "rerun-sdk", "pyarrow", "pytest",
                  "textual"):
        assert extra not in server, extra
    assert "run.sh --server-only" in (ROOT / "deploy" / "container" / "Containerfile").read_text()
    assert "run.sh --server-only" in (ROOT / "deploy" / "systemd" / "hapticproxy.service").read_text()
