"""Issue 32's papercuts, one test each where a test can see it: ``--version`` after every command,
whole help texts, status's requests in words, micrometres in ``status``, the advice a remote
device's link fault gives, a Ctrl-C the moment a command starts, a recording path blamed on the
key that named it, the client's session id and capacity."""
from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from hapticproxy.cli import main as climain

EXE = str(Path(sys.executable).parent / "hapticproxy")
ROOT = Path(__file__).resolve().parents[1]


def _every_command() -> list[list[str]]:
    out = []
    for name, cmd in climain.COMMANDS.items():
        out += [[name, t] for t in cmd.targets] if cmd.targets else [[name]]
    return out


@pytest.mark.parametrize("argv", _every_command(), ids=" ".join)
def test_version_after_every_command(argv, capsys):
    from importlib.metadata import version

    assert climain.main([*argv, "--version"]) == 0
    assert capsys.readouterr().out == f"hapticproxy {version('hapticproxy')}\n"


_OPTION = re.compile(r"^  (-\S.*?)(?:\s{2,}(\S.*))?$")


@pytest.mark.parametrize("argv", _every_command(), ids=" ".join)
def test_help_is_whole_plain_and_names_every_option(argv, capsys):
    """No reST double backticks, the description a whole sentence (not a docstring's first line
    cut mid-sentence), and every option with its help text (on its line or the next)."""
    with pytest.raises(SystemExit) as exc:
        climain.main([*argv, "--help"]) and None
        raise SystemExit(0)
    assert exc.value.code in (0, None)
    text = capsys.readouterr().out
    assert "``" not in text, text
    paras = text.split("\n\n")
    desc = next((p for p in paras[1:] if not p.startswith(("positional", "options", "  "))), "")
    assert desc.rstrip().endswith((".", ")", ":", "?")), f"description cut: {desc!r}"
    lines = text.splitlines()
    for i, ln in enumerate(lines):
        m = _OPTION.match(ln)
        if m and not m.group(2):
            nxt = lines[i + 1] if i + 1 < len(lines) else ""
            assert nxt.startswith(" " * 8) and nxt.strip() and not nxt.strip().startswith("-"), \
                f"{' '.join(argv)}: option without help: {ln.strip()!r}"


def test_status_requests_other_than_status_answer_in_words():
    from hapticproxy.server.status import format_reply

    addr = "127.0.0.1:9871"
    assert format_reply({"cmd": "rearm"}, {"ok": True, "rearm": 3}, addr).startswith("re-arm requested on 127.0.0.1:9871")
    assert format_reply({"cmd": "stop"}, {"ok": True}, addr).startswith("stop requested on 127.0.0.1:9871")
    assert format_reply({"cmd": "dump", "path": "/x/y.mcap"}, {"ok": True, "rows": 12, "path": "/x/y.mcap"},
                        addr) == "wrote 12 telemetry rows to /x/y.mcap"
    assert "{" not in format_reply({"cmd": "reset_stats"}, {"ok": True, "reset": 1}, addr)


def test_status_prints_positions_to_the_micrometre():
    """device and proxy both at 0.000125 m (one a float's rounding below): the same digits."""
    from hapticproxy.server.status import format_status

    text = format_status({"latest": {"device_pose": [0.000125, 0.0, 0.0, 1, 0, 0, 0],
                                     "proxy_pose": [0.00012499999999999998, 0.0, 0.0, 1, 0, 0, 0],
                                     "command": [0.0] * 6}})
    line = next(ln for ln in text.splitlines() if ln.startswith("device mm"))
    assert line.count("x    +0.125") == 2, line


def test_a_remote_devices_link_fault_says_it_clears_by_itself():
    from hapticproxy.protocol.devlink import DeviceFault
    from hapticproxy.server.lifecycle import Reason, describe

    text = describe(Reason.DEVICE_FAULT, float(DeviceFault.LINK))
    assert text.startswith("device fault 4 (link") and "clears by itself when the device program connects" in text
    hw = describe(Reason.DEVICE_FAULT, float(DeviceFault.HARDWARE))
    assert hw.startswith("device fault 5 (hardware)") and "re-arm" in hw


_EARLY = textwrap.dedent("""
    import os, signal, sys
    import hapticproxy.cli  # what the console script imports first
    os.kill(os.getpid(), signal.SIGINT)  # a Ctrl-C before any command code ran
    from hapticproxy.cli.main import main
    sys.exit(main(sys.argv[1:]))
""")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ctrl_c_as_serve_starts_stops_it_cleanly_and_other_commands_exit_130():
    """Papercut 5: the Ctrl-C is recorded by ``hapticproxy.cli`` and honoured when the command
    takes SIGINT over: serve stops during start-up (exit 0, nothing served), status exits 130;
    no traceback, nothing 'ignored'. Deterministic: the signal is sent before main runs."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    serve = subprocess.run([sys.executable, "-c", _EARLY, "serve", "--url", f"udp://127.0.0.1:{_free_port()}",
                            "--status", f"127.0.0.1:{_free_port()}"], capture_output=True, text=True, timeout=300,
                           env=env, preexec_fn=_default_sigint)
    assert serve.returncode == 0, serve.stderr
    assert "stopped during start-up" in serve.stderr and "serving" not in serve.stderr
    assert "Traceback" not in serve.stderr and "ignored" not in serve.stderr
    status = subprocess.run([sys.executable, "-c", _EARLY, "status", "--timeout", "0.1"], capture_output=True,
                            text=True, timeout=120, env=env, preexec_fn=_default_sigint)
    assert status.returncode == 130 and status.stderr == "hapticproxy status: interrupted\n", status.stderr


def _default_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)  # a shell's background job would ignore it


def test_a_recording_directory_that_does_not_exist_is_the_configs_error(tmp_path):
    """Papercut 11: a config's ``telemetry.record`` in a missing directory is named as that key,
    not as ``--record``, and is a configuration error (exit 2)."""
    cfg = tmp_path / "server.toml"
    cfg.write_text(f'[transport]\nurl = "udp://127.0.0.1:{_free_port()}"\n[status]\naddress = "127.0.0.1:{_free_port()}"\n'
                   f'[telemetry]\nrecord = "{tmp_path}/no/such/dir/run.mcap"\n')
    out = subprocess.run([EXE, "serve", "--config", str(cfg)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip().endswith("telemetry.record: the directory of "
                                       f"'{tmp_path}/no/such/dir/run.mcap' does not exist (the server creates none)")


def test_every_shipped_config_is_in_the_readme_and_records_mcap():
    readme = (ROOT / "README.md").read_text()
    for cfg in sorted((ROOT / "deploy" / "configs").glob("*.toml")):
        assert f"{cfg.stem}.toml" in readme, f"{cfg.name} is not in the README's table"
        import tomllib

        rec = tomllib.loads(cfg.read_text()).get("telemetry", {}).get("record", "")
        assert not rec or rec.endswith(".mcap"), f"{cfg.name}: telemetry.record {rec!r} is MCAP, name it .mcap"


def test_the_client_prints_the_session_id_as_the_server_does_and_asks_for_the_servers_capacity(helpers=None):
    """Papercut 13: the client's session line has the id in decimal (the server's log and status
    print it so), and by default it asks for the protocol's most contacts, so it is granted the
    server's capacity (a `balanced` server: 32), not its own old default of 16."""
    from hapticproxy.clients.cli import _most_contacts
    from hapticproxy.clients.contract import ProxyCommand, ScriptedServer, SimClock
    from hapticproxy.clients.runner import ClientRunner
    from hapticproxy.clients.stub_engine import StubEngine
    from hapticproxy.protocol.session import ServerConfig

    clock = SimClock()
    srv = ScriptedServer(clock, lambda t, s: ProxyCommand(s.start_pose), config=ServerConfig(max_contacts=32))
    lines: list[str] = []
    runner = ClientRunner(StubEngine(seed=1), srv.url, scene="wall", max_contacts=_most_contacts(), clock_ns=clock,
                          sleep=srv.sleep, log=lines.append)
    try:
        st = runner.run(duration_s=0.2)
    finally:
        srv.transport.close()
    sid = next(iter(srv.endpoint.sessions.values())).session_id if srv.endpoint.sessions else None
    opened = next(ln for ln in lines if ln.startswith("session "))
    assert st["granted_max_contacts"] == 32 and "max 32 contacts" in opened
    assert re.match(r"session \d+ with", opened) and "0x" not in opened
    if sid is not None:
        assert opened.startswith(f"session {sid} with")


def test_a_client_of_the_wrong_tool_kind_is_logged_by_the_server(caplog):
    """Papercut 14: the refusal the client prints is also a line in the server's log, with the
    reason; a flood of refused Hellos is one line a second, the rest counted."""
    import logging

    from hapticproxy.protocol.codec import Codec, Hello
    from hapticproxy.protocol.messages import ToolKind
    from hapticproxy.protocol.session import ServerConfig, ServerEndpoint

    sent = []
    ep = ServerEndpoint(lambda data, peer: sent.append(data), ServerConfig(supported_tools=frozenset({ToolKind.SPATIAL})))
    codec = Codec()
    with caplog.at_level(logging.WARNING, logger="hapticproxy.loop"):
        for nonce in range(1, 6):
            hello = Hello(client_nonce=nonce, tool_kind=ToolKind.PLANAR, mass_kg=1.0, max_contacts=16,
                          inertia_kg_m2=(0.0, 0.0, 1e-3, 0.0, 0.0, 0.0))
            ep.receive(codec.encode(hello), ("127.0.0.1", 40000 + nonce), 10**9)
    lines = [r.getMessage() for r in caplog.records if r.name == "hapticproxy.loop"]
    assert len(sent) == 5 and ep.counters.rejects_sent == 5
    assert len(lines) == 1, lines
    assert lines[0].startswith("refused a client at ('127.0.0.1', 40001): UNSUPPORTED_TOOL: tool kind planar not "
                               "supported by this server (it simulates spatial)")
