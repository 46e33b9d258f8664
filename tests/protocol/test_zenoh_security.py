"""deploy/zenoh/ examples: they load, and on loopback they let the right peer in and keep others out.

Certificates are generated per test session with the ``openssl`` command (P-256, a few ms);
without it the TLS loopback tests are skipped, the parse test still runs.
"""
from __future__ import annotations

import itertools
import shutil
import subprocess
from pathlib import Path

import pytest

from hapticproxy.protocol.transport import TransportError, open_transport

zenoh = pytest.importorskip("zenoh")

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy" / "zenoh"
PLACEHOLDER_DIR = "/etc/hapticproxy/zenoh/"
_serial = itertools.count(1)
REFUSE_TIMEOUT_S = 1.0  # how long a refused client keeps trying before open() gives up


def _materialise(name: str, directory: Path, replace: dict[str, str] | None = None) -> Path:
    """Copy a deploy config with its placeholder paths pointing into ``directory``."""
    text = (DEPLOY / name).read_text().replace(PLACEHOLDER_DIR, f"{directory}/")
    for old, new in (replace or {}).items():
        assert old in text, f"{old!r} not in {name}"
        text = text.replace(old, new)
    out = directory / f"materialised-{next(_serial)}-{name}"
    out.write_text(text)
    return out


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("openssl command not available to generate test certificates")
    d = tmp_path_factory.mktemp("pki")

    def run(*args: str) -> None:
        subprocess.run([openssl, *args], cwd=d, check=True, capture_output=True, timeout=60)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"]
    run("req", "-x509", *ec, "-keyout", "ca-key.pem", "-out", "ca.pem", "-days", "2", "-subj", "/CN=test CA")
    run("req", "-x509", *ec, "-keyout", "rogue-ca-key.pem", "-out", "rogue-ca.pem", "-days", "2", "-subj", "/CN=rogue")
    ext = "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth,clientAuth\n"
    for who, ca in (("server", "ca"), ("client", "ca"), ("rogue-client", "rogue-ca")):
        run("req", *ec, "-keyout", f"{who}-key.pem", "-out", f"{who}.csr", "-subj", f"/CN={who}")
        (d / f"{who}.ext").write_text(ext)
        run(
            "x509", "-req", "-in", f"{who}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}-key.pem",
            "-CAcreateserial", "-days", "2", "-out", f"{who}.pem", "-extfile", f"{who}.ext",
        )
    (d / "credentials.txt").write_text((DEPLOY / "credentials.txt.example").read_text())
    return d


def test_every_example_config_loads(tmp_path):
    names = sorted(p.name for p in DEPLOY.glob("*.json5"))
    assert names == ["tls-client.json5", "tls-server.json5", "usrpwd-client.json5", "usrpwd-server.json5"]
    for name in names:
        cfg = zenoh.Config.from_file(str(_materialise(name, tmp_path)))
        # The documented keys are really there (a typo'd key would simply be missing).
        if name.startswith("tls"):
            tls = cfg.get_json("transport/link/tls")
            assert '"enable_mtls":true' in tls.replace(" ", "")
            assert str(tmp_path) in cfg.get_json("transport/link/tls/root_ca_certificate")
        else:
            assert cfg.get_json("transport/auth/usrpwd") != "null"


def _exchange(server, client) -> bool:
    import time

    client.send(b"secure-hello")
    deadline = time.monotonic() + 10
    while (got := server.recv()) is None and time.monotonic() < deadline:
        time.sleep(0.0005)
    if got is None or got[0] != b"secure-hello":
        return False
    server.send(b"secure-ack", got[1])
    while (ack := client.recv()) is None and time.monotonic() < deadline:
        time.sleep(0.0005)
    return ack is not None and ack[0] == b"secure-ack"


def test_mutual_tls_lets_the_right_client_in_and_keeps_others_out(pki):
    server_cfg = _materialise("tls-server.json5", pki)
    client_cfg = _materialise("tls-client.json5", pki)
    no_cert_cfg = _materialise(
        "tls-client.json5",
        pki,
        {f'connect_certificate: "{pki}/client.pem",': "", f'connect_private_key: "{pki}/client-key.pem",': ""},
    )
    rogue_cfg = _materialise(
        "tls-client.json5",
        pki,
        {f'"{pki}/client.pem"': f'"{pki}/rogue-client.pem"', f'"{pki}/client-key.pem"': f'"{pki}/rogue-client-key.pem"'},
    )
    with open_transport(f"zenoh://127.0.0.1:0/tls?protocol=tls&config={server_cfg}", role="server") as server:
        assert server.endpoint.startswith("tls/127.0.0.1:")
        with open_transport(f"{server.url}&config={client_cfg}", role="client") as client:
            assert _exchange(server, client)
        for cfg in (no_cert_cfg, rogue_cfg):
            with pytest.raises(TransportError):
                open_transport(f"{server.url}&config={cfg}", role="client", connect_timeout_s=REFUSE_TIMEOUT_S)
        # Plain TCP to the TLS port is not a way in either.
        port = server.endpoint.rsplit(":", 1)[1]
        with pytest.raises(TransportError):
            open_transport(f"zenoh://127.0.0.1:{port}/tls", role="client", connect_timeout_s=REFUSE_TIMEOUT_S)
        assert server.counters.received == 1


def test_user_password_lets_the_right_client_in_and_keeps_others_out(pki):
    server_cfg = _materialise("usrpwd-server.json5", pki)
    client_cfg = _materialise("usrpwd-client.json5", pki)
    wrong_cfg = _materialise("usrpwd-client.json5", pki, {"CHANGE-ME-engine-password": "not-the-password"})
    with open_transport(f"zenoh://127.0.0.1:0/pw?config={server_cfg}", role="server") as server:
        with open_transport(f"{server.url}?config={client_cfg}", role="client") as client:
            assert _exchange(server, client)
        with pytest.raises(TransportError):
            open_transport(f"{server.url}?config={wrong_cfg}", role="client", connect_timeout_s=REFUSE_TIMEOUT_S)
        with pytest.raises(TransportError):  # no credentials at all
            open_transport(server.url, role="client", connect_timeout_s=REFUSE_TIMEOUT_S)
        assert server.counters.received == 1


def test_missing_config_file_is_a_value_error(tmp_path):
    with pytest.raises(ValueError, match="config file not found"):
        open_transport(f"zenoh://127.0.0.1:0/x?config={tmp_path}/nope.json5", role="server")


# ----------------------------------------------------------------------------------------------
# The real server (supervisor + haptic-loop process) behind each secure configuration: the right
# client opens a session and its contacts drive the model; a client without the right credentials
# cannot open a link, so no Hello or ContactUpdate of its ever reaches the server (not even one
# that would be refused: the server's receive counters see only the good client's datagrams).


def _tcp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _secure_server_run(server_url: str, good_url: str, bad_urls: list[str]) -> tuple[dict, dict, list]:
    """Start the real server on ``server_url``, a stub testbed client on ``good_url``; once it
    drives the model, every ``bad_urls`` client tries to join (and would send contacts). Returns
    the server status before and after the bad attempts and what each bad attempt raised."""
    import threading
    import time

    from hapticproxy.clients.runner import ClientError, ClientRunner
    from hapticproxy.clients.stub_engine import StubEngine
    from hapticproxy.server import config as cfgmod
    from hapticproxy.server.daemon import Supervisor

    settings = cfgmod.load({
        "loop": {"rate_hz": 1000.0, "realtime": False},
        "transport": {"url": server_url},
        "status": {"address": f"127.0.0.1:{_udp_port()}"},
        "device": {"driver": "sim", "kind": "planar", "watchdog_s": 0.5, "workspace_min_m": [-0.25, -0.25],
                   "workspace_max_m": [0.25, 0.25], "hand": {"type": "constant", "wrench": [0.0, 0.5, 0.0]}},
    })
    sup = Supervisor(settings)
    engine = StubEngine(seed=3)
    stop = threading.Event()
    good = ClientRunner(engine, good_url, scene="testbed", connect_timeout_s=60.0)
    th = threading.Thread(target=lambda: good.run(stop), daemon=True)
    outcomes = []
    try:
        sup.start()
        th.start()
        t_end = time.monotonic() + 60
        while sup.shared.snapshot()["updates"] < 30 and time.monotonic() < t_end:
            sup._serve_status(0.05)
        before = sup.shared.snapshot()
        for url in bad_urls:
            bad_engine = StubEngine(seed=4)
            bad = ClientRunner(bad_engine, url, scene="testbed", connect_timeout_s=REFUSE_TIMEOUT_S + 2.0,
                               reconnect=False, transport_options={"connect_timeout_s": REFUSE_TIMEOUT_S})
            try:
                bad.run()
                outcomes.append(None)
            except ClientError as exc:
                outcomes.append(exc)
            finally:
                bad_engine.close()
            outcomes[-1] = (outcomes[-1], bad.stats()["updates_sent"], bad.stats()["hellos_sent"])
        t_end = time.monotonic() + 30
        while sup.shared.snapshot()["updates"] < before["updates"] + 30 and time.monotonic() < t_end:
            sup._serve_status(0.05)
        after = sup.shared.snapshot()
    finally:
        stop.set()
        th.join(15)
        engine.close()
        sup.close()
    return before, after, outcomes


def _assert_only_the_good_client_got_in(before: dict, after: dict, outcomes: list) -> None:
    for err, updates_sent, hellos_sent in outcomes:
        assert err is not None and "no session" in str(err)  # refused at the link: never a session
        assert updates_sent == 0 and hellos_sent == 0  # nothing could even be sent
    assert after["sessions_opened"] == before["sessions_opened"] == 1
    assert after["updates"] > before["updates"] >= 30 and after["faults_total"] == 0
    # not one foreign datagram reached the session layer, refused or not
    for k in ("decode_errors", "unknown_session", "bad_token", "wrong_peer", "unexpected", "rejects_sent",
              "stale_or_duplicate"):
        assert after[k] == 0, k


def test_mutual_tls_server_accepts_only_a_client_with_a_certificate_of_its_ca(pki):
    server_cfg = _materialise("tls-server.json5", pki)
    client_cfg = _materialise("tls-client.json5", pki)
    no_cert_cfg = _materialise(
        "tls-client.json5", pki,
        {f'connect_certificate: "{pki}/client.pem",': "", f'connect_private_key: "{pki}/client-key.pem",': ""})
    rogue_cfg = _materialise(
        "tls-client.json5", pki,
        {f'"{pki}/client.pem"': f'"{pki}/rogue-client.pem"', f'"{pki}/client-key.pem"': f'"{pki}/rogue-client-key.pem"'})
    base = f"zenoh://127.0.0.1:{_tcp_port()}/mtls"
    before, after, outcomes = _secure_server_run(
        f"{base}?protocol=tls&config={server_cfg}", f"{base}?protocol=tls&config={client_cfg}",
        [f"{base}?protocol=tls&config={no_cert_cfg}", f"{base}?protocol=tls&config={rogue_cfg}", base])
    _assert_only_the_good_client_got_in(before, after, outcomes)


def test_user_password_server_accepts_only_a_client_with_the_password(pki):
    server_cfg = _materialise("usrpwd-server.json5", pki)
    client_cfg = _materialise("usrpwd-client.json5", pki)
    wrong_cfg = _materialise("usrpwd-client.json5", pki, {"CHANGE-ME-engine-password": "not-the-password"})
    base = f"zenoh://127.0.0.1:{_tcp_port()}/pw"
    before, after, outcomes = _secure_server_run(
        f"{base}?config={server_cfg}", f"{base}?config={client_cfg}", [f"{base}?config={wrong_cfg}", base])
    _assert_only_the_good_client_got_in(before, after, outcomes)
