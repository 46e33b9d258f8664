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
