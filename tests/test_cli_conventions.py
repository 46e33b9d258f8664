"""Command-line conventions of every command (issue 17, section 4) and the one plug-in registry of
engines, device drivers and transports (issue 14, item 6).

- ``--version``; ``-v``/``--log-level`` before or after the command, inherited by the loop
  process; timestamps in every log line; the supervisor and the loop process named in ``ps``;
- strict JSON (no NaN, integers as integers) from status, client, bench and plugins;
- exit codes: a taken or unassignable address named in one line (1 taken, 2 not assignable),
  Ctrl-C or SIGTERM during start-up stops cleanly (exit 0, no traceback), ``status | head``;
- plug-ins from another package's entry points: a transport scheme and a device driver that
  work end to end, a built-in name that cannot be taken over, one ``hapticproxy plugins`` list.
"""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from hapticproxy.cli import main as climain
from hapticproxy.protocol import logs
from hapticproxy.protocol.jsonout import dumps
from hapticproxy.server.status import query

EXE = str(Path(sys.executable).parent / "hapticproxy")
#: a log line: local ISO time with ms, then the program
LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3} hapticproxy (serve|loop|client|device|warmup): ")


def run(*args, env=None, timeout=300):
    return subprocess.run([EXE, *args], capture_output=True, text=True, timeout=timeout, env=env)


def strict_json(text: str):
    """``json.loads`` that refuses NaN and Infinity (Python's parser accepts them by default)."""
    def refuse(const):
        raise ValueError(f"not strict JSON: {const}")

    return json.loads(text, parse_constant=refuse)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def children(pid: int) -> dict[int, str]:
    """The child processes of ``pid``: pid -> command line as ``ps`` shows it."""
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out[int(d)] = Path(f"/proc/{d}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
        except (OSError, ValueError, IndexError):
            continue
    return out


# ----------------------------------------------------------------------------- global options
def test_version_is_the_installed_distributions():
    from importlib.metadata import version

    out = run("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"hapticproxy {version('hapticproxy')}"


@pytest.mark.parametrize("argv, verbose, level, command, rest", [
    (["-v", "serve", "--config", "x.toml"], 1, None, "serve", ["--config", "x.toml"]),
    (["serve", "-vv", "--config", "x.toml", "-v"], 3, None, "serve", ["--config", "x.toml"]),
    (["--log-level", "debug", "status", "--json"], 0, "debug", "status", ["--json"]),
    (["client", "stub", "--log-level=warning", "--epsilon=-0.001"], 0, "warning", "client", ["stub", "--epsilon=-0.001"]),
    (["client", "stub", "--", "-v"], 0, None, "client", ["stub", "--", "-v"]),
    (["bench", "model", "--verbose", "--json"], 1, None, "bench", ["model", "--json"]),
])
def test_global_options_stand_before_or_after_the_command(argv, verbose, level, command, rest):
    g, cmd, args = climain.split_global(argv)
    assert (g.verbose, g.log_level, cmd, args) == (verbose, level, command, rest)


def test_bad_global_options_are_one_line_and_exit_2():
    for argv, needle in ((["--log-level", "loud", "status"], "--log-level: expected one of debug"),
                         (["--frob", "status"], "unknown option '--frob'"),
                         (["status", "--log-level"], "--log-level needs a level")):
        out = run(*argv)
        assert out.returncode == 2 and needle in out.stderr and "Traceback" not in out.stderr, out.stderr
        assert out.stderr.count("\n") == 1


def test_the_log_level_follows_the_defaults_and_the_options(monkeypatch):
    import logging

    for env, default, quiet, want in (({}, logging.INFO, 0, logging.INFO),
                                      ({logs.ENV_VERBOSE: "1"}, logging.INFO, 0, logging.DEBUG),
                                      ({logs.ENV_VERBOSE: "1"}, logging.WARNING, 0, logging.INFO),
                                      ({}, logging.INFO, 1, logging.WARNING),
                                      ({logs.ENV_LEVEL: "error", logs.ENV_VERBOSE: "2"}, logging.INFO, 0, logging.ERROR)):
        monkeypatch.delenv(logs.ENV_LEVEL, raising=False)
        monkeypatch.delenv(logs.ENV_VERBOSE, raising=False)
        for k, v in env.items():
            monkeypatch.setenv(k, v)
        assert logs.effective_level(default, quiet)[0] == want, env


def test_every_command_of_the_table_has_a_main():
    import importlib

    for name, cmd in climain.COMMANDS.items():
        for module in (cmd.targets.values() if cmd.targets else [cmd.module]):
            assert callable(importlib.import_module(module).main), (name, module)


def test_status_does_not_import_numba():
    code = ("import sys; from hapticproxy.cli.main import main; "
            f"rc = main(['status', '--address', '127.0.0.1:{free_udp_port()}', '--timeout', '0.1']); "
            "print(rc, 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["1", "False"], out.stderr


def test_strict_json_of_every_kind_of_value():
    import math

    import numpy as np

    text = dumps({"nan": math.nan, "inf": np.float64(np.inf), "count": np.int64(3), "arr": np.array([1.5, np.nan]),
                  "flag": np.bool_(True), "t": (1, 2.0)})
    assert strict_json(text) == {"nan": None, "inf": None, "count": 3, "arr": [1.5, None], "flag": True, "t": [1, 2.0]}
    assert '"count": 3,' in text  # an integer, not 3.0


def test_bench_json_is_strict():
    out = run("bench", "codec", "--json", "--batch", "5", "--repeats", "3")
    assert out.returncode == 0, out.stderr
    rows = strict_json(out.stdout)
    assert rows and all(isinstance(r["naive_bytes"], int) for r in rows)


# ----------------------------------------------------------------------------- a running server
@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """One ``hapticproxy serve`` for the tests that need a running server: (process, url, status)."""
    url, status = f"udp://127.0.0.1:{free_udp_port()}", f"127.0.0.1:{free_udp_port()}"
    err = tmp_path_factory.mktemp("serve") / "stderr.txt"
    with open(err, "w") as fh:
        proc = subprocess.Popen([EXE, "serve", "--url", url, "--status", status], stdout=subprocess.DEVNULL, stderr=fh,
                                text=True)
    try:
        t_end = time.monotonic() + 240
        while True:
            assert proc.poll() is None, err.read_text()
            try:
                if query(status, timeout_s=0.3).get("ready") == 1.0:
                    break
            except TimeoutError:
                pass
            assert time.monotonic() < t_end, "the server never became ready"
        yield proc, url, status, err
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(30)


def test_the_supervisor_and_the_loop_process_are_named_in_ps(served):
    proc, url, status, _ = served
    cmdline = Path(f"/proc/{proc.pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    assert cmdline.startswith(f"hapticproxy serve --url {url} --status {status}")
    assert "hapticproxy-loop" in children(proc.pid).values()


def test_status_json_is_strict_with_integer_counters(served):
    _, _, status, _ = served
    out = run("status", "--address", status, "--json")
    assert out.returncode == 0, out.stderr
    s = strict_json(out.stdout)
    for key in ("steps", "overruns", "missed_deadlines", "session_id", "contacts", "fault", "updates"):
        assert type(s[key]) is int, (key, s[key])


@pytest.mark.parametrize("reader", ["head -1", "head -c 5"])
@pytest.mark.parametrize("json_flag", ["", "--json"])
def test_status_into_a_reader_that_leaves_does_not_trace_back(served, reader, json_flag):
    _, _, status, _ = served
    out = subprocess.run(f"{EXE} status --address {status} {json_flag} | {reader} >/dev/null; "
                         "echo ${PIPESTATUS[0]}", shell=True, executable="/bin/bash", capture_output=True, text=True,
                         timeout=60)
    assert out.stdout.strip() == "0" and "Traceback" not in out.stderr and "Error" not in out.stderr, out.stderr


def test_the_client_logs_with_timestamps_and_prints_strict_json(served):
    _, url, _, _ = served
    out = run("client", "stub", "--scene", "wall", "--connect", url, "--duration", "0.5", "--json")
    assert out.returncode == 0, out.stderr
    st = strict_json(out.stdout)
    assert st["sessions"] == 1 and isinstance(st["steps"], int) and st["steps"] > 0
    lines = out.stderr.splitlines()
    assert lines and all(LOG_LINE.match(ln) for ln in lines), out.stderr
    quiet = run("--log-level", "warning", "client", "stub", "--scene", "wall", "--connect", url, "--duration", "0.3")
    assert quiet.returncode == 0 and quiet.stderr == ""


@pytest.mark.parametrize("which", ["transport", "status"])
def test_a_taken_address_is_named_in_one_line_and_exit_1(served, which):
    _, url, status, _ = served
    args = ["--url", url, "--status", f"127.0.0.1:{free_udp_port()}"] if which == "transport" else \
        ["--url", f"udp://127.0.0.1:{free_udp_port()}", "--status", status]
    out = run("serve", *args)
    taken = url if which == "transport" else status
    assert out.returncode == 1
    assert out.stderr == f"hapticproxy serve: {which}.{'url' if which == 'transport' else 'address'} {taken}: " \
                         "address already in use (another server running?)\n"


def test_the_servers_log_lines_have_timestamps(served):
    *_, err = served
    lines = [ln for ln in err.read_text().splitlines() if ln.strip()]
    assert any("serving: udp://" in ln for ln in lines)
    assert all(LOG_LINE.match(ln) for ln in lines), lines


def test_port_0_serving_line_names_the_ports_the_system_picked():
    """``--url udp://127.0.0.1:0 --status 127.0.0.1:0``: the one line a person reads names the
    ports to connect to, not port 0."""
    out = run("serve", "--url", "udp://127.0.0.1:0", "--status", "127.0.0.1:0", "--duration", "0.3")
    assert out.returncode == 0, out.stderr
    m = re.search(r"serving: udp://127\.0\.0\.1:(\d+) at .* status on 127\.0\.0\.1:(\d+)", out.stderr)
    assert m and int(m.group(1)) > 0 and int(m.group(2)) > 0, out.stderr


# ----------------------------------------------------------------------------- without a server
@pytest.mark.parametrize("which", ["transport", "status"])
def test_an_address_this_machine_does_not_have_is_named_and_exit_2(which):
    # 192.0.2.1 (TEST-NET-1, RFC 5737) is on no interface: the bind fails here, nothing is sent
    args = ["--url", "udp://192.0.2.1:9870", "--status", f"127.0.0.1:{free_udp_port()}"] if which == "transport" else \
        ["--url", f"udp://127.0.0.1:{free_udp_port()}", "--status", "192.0.2.1:9871"]
    out = run("serve", *args)
    name = "transport.url udp://192.0.2.1:9870" if which == "transport" else "status.address 192.0.2.1:9871"
    assert out.returncode == 2
    assert out.stderr == f"hapticproxy serve: {name}: not an address of this machine (cannot assign it)\n"


def test_a_taken_zenoh_address_is_named_without_zenohs_source_paths():
    pytest.importorskip("zenoh")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        url = f"zenoh://127.0.0.1:{busy.getsockname()[1]}/taken"
        out = run("serve", "--url", url, "--status", f"127.0.0.1:{free_udp_port()}")
    assert out.returncode == 1
    assert out.stderr == f"hapticproxy serve: transport.url {url}: address already in use (another server running?)\n"


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_a_stop_during_start_up_is_clean(how):
    """Ctrl-C in the terminal (SIGINT to the whole process group) or SIGTERM to the supervisor
    while the loop process is starting (importing, building, loading or compiling its kernels):
    the loop process is stopped before it runs, exit 0, no traceback, nothing left behind."""
    status = f"127.0.0.1:{free_udp_port()}"
    proc = subprocess.Popen([EXE, "serve", "--url", f"udp://127.0.0.1:{free_udp_port()}", "--status", status],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        t_end = time.monotonic() + 120
        loop_pid = None
        while loop_pid is None:
            assert proc.poll() is None and time.monotonic() < t_end
            loop_pid = next((pid for pid, cmd in children(proc.pid).items() if cmd == "hapticproxy-loop"), None)
            time.sleep(0.005)
        if query(status, timeout_s=2.0).get("ready") == 1.0:
            pytest.skip("the loop process was ready before it could be interrupted")
        if how == "ctrl-c":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "stopping during start-up" in err and "stopped cleanly" in err, err
    assert not Path(f"/proc/{loop_pid}").exists()


# ----------------------------------------------------------------------------- plug-ins
LAB_MODULE = '''"""A lab's own transport and device driver, from its own package (a test fixture)."""
from hapticproxy.protocol.transport.mem import MemTransport
from hapticproxy.server.devices.sim import make_sim_device


class LabBusTransport(MemTransport):
    scheme = "labbus"


class NotATransport:
    url_form = "name"


def make_lab_device(config, *, period_s, clock_ns=None):
    dev = make_sim_device(config, period_s=period_s, clock_ns=clock_ns)
    dev.name = "labdev"
    return dev
'''


def make_plugin_package(root: Path) -> Path:
    """An installed package ``labplug`` in ``root`` (put it on sys.path): a transport ``labbus``,
    a device ``labdev``, a transport entry that is no Transport, and one that tries to take
    ``udp``."""
    (root / "labplug.py").write_text(LAB_MODULE)
    info = root / "labplug-0.1.dist-info"
    info.mkdir(exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: labplug\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(textwrap.dedent("""\
        [hapticproxy.transports]
        labbus = labplug:LabBusTransport
        broken = labplug:NotATransport
        udp = labplug:LabBusTransport

        [hapticproxy.devices]
        labdev = labplug:make_lab_device
        """))
    return root


@pytest.fixture
def plugins(tmp_path, monkeypatch):
    make_plugin_package(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_a_transport_of_another_package_works_by_its_scheme(plugins):
    from hapticproxy.protocol.transport import TRANSPORT_REGISTRY, UdpTransport, open_transport

    entries = TRANSPORT_REGISTRY.entries()
    assert list(entries) == ["mem", "udp", "zenoh", "broken", "labbus"]
    assert entries["labbus"].package == "labplug 0.1" and not entries["labbus"].builtin
    assert entries["udp"].builtin and entries["udp"].ignored == ("labplug 0.1: labplug:LabBusTransport",)
    with open_transport("labbus://lab-1", role="server") as server, \
            open_transport("labbus://lab-1?queue_capacity=4", role="client") as client:
        assert type(server).__name__ == "LabBusTransport" and client.url == "labbus://lab-1"
        client.send(b"hello")
        got = server.recv()
        assert got is not None and got[0] == b"hello"
    with open_transport("udp://127.0.0.1:0", role="server") as u:
        assert type(u) is UdpTransport  # the built-in keeps its scheme
    assert "is not a Transport subclass" in TRANSPORT_REGISTRY.availability("broken")
    with pytest.raises(ValueError, match="scheme must be one of mem, udp, zenoh, broken, labbus; got 'tcp'"):
        open_transport("tcp://127.0.0.1:1")


def test_a_device_of_another_package_is_built_and_configured_by_name(plugins):
    from hapticproxy.server import config as cfgmod
    from hapticproxy.server.devices.base import DEVICE_REGISTRY, load_device

    assert DEVICE_REGISTRY.entries()["labdev"].package == "labplug 0.1"
    dev = load_device("labdev", {"kind": "planar"}, period_s=1e-3)
    try:
        assert dev.name == "labdev" and dev.kind == "planar"
    finally:
        dev.close()
    settings = cfgmod.load(None, {"device": {"driver": "labdev", "kind": "planar"}})
    assert settings["device"]["driver"] == "labdev"
    with pytest.raises(cfgmod.ConfigError, match="device.driver: unknown device 'nosuch'; choose one of: "
                                                  "forcedimension, haply, remote, sim, touch, labdev"):
        cfgmod.load(None, {"device": {"driver": "nosuch"}})


def test_plugins_lists_every_kind_with_its_package(tmp_path):
    make_plugin_package(tmp_path)
    env = dict(os.environ, PYTHONPATH=str(tmp_path))
    out = run("plugins", "--kind", "transport", "--kind", "device", env=env)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "transports (hapticproxy.transports):"
    assert any(ln.split()[:1] == ["labbus"] and "(labplug 0.1)" in ln and "url: labbus://name" in ln for ln in lines)
    assert any(ln.split()[:1] == ["broken"] and "not available: transport 'broken'" in ln for ln in lines)
    assert "ignored, the name is taken: labplug 0.1: labplug:LabBusTransport" in out.stdout
    assert "devices (hapticproxy.devices):" in lines and any(ln.split()[:1] == ["labdev"] for ln in lines)
    rows = strict_json(run("plugins", "--json", env=env).stdout)
    kinds = {(r["kind"], r["name"]): r for r in rows}
    assert {("engine", "stub"), ("device", "sim"), ("device", "labdev"), ("transport", "zenoh")} <= set(kinds)
    assert kinds[("engine", "stub")]["builtin"] and "testbed" in kinds[("engine", "stub")]["scenes"]
    assert not kinds[("transport", "broken")]["available"]


def test_listing_the_engines_prints_nothing_but_the_listing():
    """The engines' scenes are read from their classes (pybullet imported): its C extension's
    build-date line must reach neither stream."""
    out = run("plugins", "--kind", "engine")
    assert out.returncode == 0 and out.stderr == "", out.stderr
    assert any(ln.split()[:1] == ["pybullet"] for ln in out.stdout.splitlines()) and "build time" not in out.stdout


def test_the_log_level_reaches_the_loop_process():
    """``-v`` shows the debug lines of the supervisor and of the loop process (which inherits the
    level); ``--log-level warning`` hides the info lines of both."""
    args = ["--url", f"udp://127.0.0.1:{free_udp_port()}", "--status", f"127.0.0.1:{free_udp_port()}", "--duration", "0.2"]
    out = run("-v", "serve", *args)
    assert out.returncode == 0, out.stderr
    assert re.search(r"hapticproxy serve: debug: loop process \d+ started", out.stderr)
    assert re.search(r"hapticproxy loop: debug: pid \d+: transport udp://127\.0\.0\.1:\d+ open", out.stderr)
    quiet = run("serve", *args, "--log-level", "warning")
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
