"""Record ``session_v1_1.jsonl``: every datagram of one real session, as a plain UDP relay between
a client and a server passes it (JSON lines: ``t_s``, ``dir``, ``hex``; no project import, so it
records any two peers). The file in the repository was recorded on 2026-12-04 from the
pre-restructure tree (6638e56, the hand-written codec, protocol 1.1), ``tests/protocol/
test_recorded_session.py`` replays it through today's codec::

    hapticproxy serve --config deploy/configs/udp-loopback.toml                    # port 9870
    python tests/protocol/golden/record_session.py 9880 9870 session_v1_1.jsonl 12
    hapticproxy client pymunk --scene testbed --connect udp://127.0.0.1:9880 --duration 3
"""
import json
import select
import socket
import sys
import time


def main(listen_port: int, upstream_port: int, out_path: str, seconds: float) -> None:
    a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    a.bind(("127.0.0.1", listen_port))
    b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    b.bind(("127.0.0.1", 0))
    upstream = ("127.0.0.1", upstream_port)
    client = None
    t0 = time.monotonic()
    with open(out_path, "w") as f:
        while time.monotonic() - t0 < seconds:
            ready, _, _ = select.select([a, b], [], [], 0.1)
            for s in ready:
                data, peer = s.recvfrom(65536)
                t = round(time.monotonic() - t0, 6)
                if s is a:
                    client = peer
                    b.sendto(data, upstream)
                    f.write(json.dumps({"t_s": t, "dir": "client->server", "hex": data.hex()}) + "\n")
                elif client is not None:
                    a.sendto(data, client)
                    f.write(json.dumps({"t_s": t, "dir": "server->client", "hex": data.hex()}) + "\n")
    a.close()
    b.close()


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], float(sys.argv[4]))
