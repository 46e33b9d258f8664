"""The engine-neutral client loop against the protocol's reference server (and small fake servers
where a test needs to misbehave on purpose): handshake, one ContactUpdate per step, newest
ProxyState, grants, heartbeats, reconnection, vanishing servers, refusals."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from hapticproxy.clients.runner import ClientError, ClientRunner
from hapticproxy.clients.stub_engine import StubEngine
from hapticproxy.protocol.codec import Codec, Hello, ProxyState, Reject
from hapticproxy.protocol.messages import ErrorCode, ToolKind
from hapticproxy.protocol.session import ServerConfig, ServerEndpoint
from hapticproxy.protocol.transport import open_transport

KEY = bytes(range(40, 72))


def _url(scheme: str, free_port, name: str) -> str:
    if scheme == "mem":
        return f"mem://{name}"
    if scheme == "udp":
        return "udp://127.0.0.1:0"
    return f"zenoh://127.0.0.1:{free_port()}/{name}"


@pytest.mark.parametrize("scheme", ["mem", "udp", "zenoh"])
def test_handshake_and_updates_both_ways(scheme, server_thread, helpers):
    srv = server_thread(_url(scheme, helpers.free_udp_port, f"both-{scheme}"))
    engine = StubEngine(seed=1)
    runner = ClientRunner(engine, srv.url, scene="testbed", realtime=False, connect_timeout_s=10.0,
                          transport_options={"connect_timeout_s": 5.0} if scheme == "zenoh" else None)
    st = runner.run(max_steps=300)
    srv.wait_for_bye()
    srv.stop()
    assert st["state"] == "stopped" and st["error"] is None and st["end_reason"] == "max_steps reached"
    assert st["sessions"] == 1 and st["steps"] == 300 and st["updates_sent"] == 300
    assert st["granted_epsilon_m"] == 0.005 and st["granted_max_contacts"] == 16
    # server -> client: acknowledgements came back and drove the tool
    assert st["proxy_states"] > 0 and st["proxy_applied"] > 0
    assert st["proxy_states"] == st["proxy_applied"] + st["proxy_superseded"]
    # client -> server: the updates arrived in order, from seq 1
    seqs = [u.seq for u in srv.updates]
    assert seqs and seqs[0] == 1 and all(b > a for a, b in zip(seqs, seqs[1:]))
    assert len(seqs) >= 0.9 * 300 if scheme != "mem" else seqs == list(range(1, 301))
    assert srv.endpoint.counters.byes_received == 1  # the runner said goodbye when it stopped


def test_one_contact_update_after_every_engine_step(server_thread, helpers):
    srv = server_thread("mem://every-step")
    engine = helpers.RecordingEngine(rate_hz=100.0, n_contacts=3)
    runner = ClientRunner(engine, srv.url, scene="floor", realtime=False)
    st = runner.run(max_steps=50)
    srv.wait_for_bye()
    srv.stop()
    ups = srv.updates
    assert engine.steps == st["steps"] == 50
    assert [u.seq for u in ups] == list(range(1, 51))
    times = [u.env_time_s for u in ups]
    assert times == pytest.approx([0.01 * (i + 1) for i in range(50)])  # the engine clock, step by step
    assert all(u.n_contacts == 3 for u in ups)


def test_realtime_loop_never_runs_ahead_of_the_wall_clock(server_thread, helpers):
    srv = server_thread("mem://realtime")
    engine = helpers.RecordingEngine(rate_hz=200.0)
    runner = ClientRunner(engine, srv.url, scene="floor")
    t0 = time.monotonic()
    st = runner.run(duration_s=0.4)
    elapsed = time.monotonic() - t0
    assert st["steps"] > 0
    assert engine.time_s <= elapsed + 1.0 / 200.0


def test_newest_proxy_state_is_applied_and_stale_ones_dropped(runner_thread, helpers):
    """A fake server sends ProxyStates out of order and in bursts: the engine only ever sees
    newer ones, and the last it sees is the newest."""
    srv_t = open_transport("mem://newest", role="server")
    server = ServerEndpoint(srv_t.send)
    codec = Codec()
    engine = helpers.RecordingEngine(rate_hz=20.0)
    rt = runner_thread(ClientRunner(engine, "mem://newest", scene="floor"))
    session = {}

    def pump():
        for data, peer in srv_t.drain():
            up = server.receive(data, peer)
            if up is not None:
                session.update(sid=up.session_id, peer=peer, seq=up.seq)

    def proxy(seq, y):
        s = server.sessions[session["sid"]]
        return codec.encode(ProxyState(seq=seq, ack_seq=session["seq"], server_time_s=0.0,
                                       proxy_pose=np.array([0.0, y, 0.0, 1.0, 0.0, 0.0, 0.0]), proxy_twist=np.zeros(6),
                                       wrench=np.zeros(6), session_id=s.session_id, token=s.token))

    try:
        helpers.wait_for(lambda: (pump(), session.get("seq", 0) >= 2)[1], what="two updates")
        peer = session["peer"]
        srv_t.send(proxy(10, 0.10), peer)
        helpers.wait_for(lambda: len(engine.driven) >= 1, what="first proxy state")
        srv_t.send(proxy(9, 0.09), peer)  # stale
        srv_t.send(proxy(10, 0.101), peer)  # duplicate
        for burst in range(5):  # three at once: only the newest of what arrived together is applied
            for k in range(3):
                srv_t.send(proxy(11 + 3 * burst + k, 0.2 + 0.01 * (3 * burst + k)), peer)
            newest_y = 0.2 + 0.01 * (3 * burst + 2)
            helpers.wait_for(lambda: engine.driven and engine.driven[-1][1] == newest_y, what="burst applied")
        rt.stop()
    finally:
        srv_t.close()
    ys = [p[1] for p in engine.driven]
    assert 0.09 not in ys and 0.101 not in ys
    assert all(b > a for a, b in zip(ys, ys[1:]))  # never backwards
    assert ys[-1] == pytest.approx(0.2 + 0.01 * 14)
    st = rt.result
    assert st["stale"] >= 1 and st["duplicate"] >= 1
    assert st["proxy_states"] == 16 == st["proxy_applied"] + st["proxy_superseded"]
    assert st["proxy_superseded"] >= 1  # bursts read in one go drove the engine once


def test_granted_epsilon_and_capacity_are_used(server_thread):
    srv = server_thread("mem://grants", config=ServerConfig(max_epsilon_m=0.002, max_contacts=2))
    engine = StubEngine(seed=2)
    runner = ClientRunner(engine, srv.url, scene="hole", epsilon_m=0.005, max_contacts=16, realtime=False)
    st = runner.run(max_steps=40)
    srv.wait_for_bye()
    srv.stop()
    assert st["granted_epsilon_m"] == 0.002 and st["granted_max_contacts"] == 2
    assert engine._eps == 0.002
    ups = srv.updates
    assert len(ups) == 40 and max(u.n_contacts for u in ups) == 2
    # the peg resting in the hole touches more than two features (the reference server's proxy at
    # the origin soon pulls it out, so only the first steps cluster)
    assert st["steps_clustered"] > 0


def test_heartbeats_keep_a_slow_engine_session_alive(server_thread, helpers):
    cfg = ServerConfig(heartbeat_interval_s=0.05, silence_timeout_s=0.3)
    srv = server_thread("mem://slow", config=cfg)
    engine = helpers.RecordingEngine(rate_hz=2.0)  # a step every 0.5 s: longer than the silence timeout
    runner = ClientRunner(engine, srv.url, scene="floor")
    st = runner.run(duration_s=1.3)
    srv.stop()
    assert st["heartbeats_sent"] >= 3
    assert st["sessions"] == 1 and st["sessions_ended"] == 0
    assert srv.endpoint.counters.timeouts == 0


@pytest.mark.parametrize("scheme", ["udp", "mem", "zenoh"])
def test_reconnects_after_the_server_restarts(scheme, server_thread, runner_thread, helpers):
    url = {"udp": f"udp://127.0.0.1:{helpers.free_udp_port()}", "mem": "mem://restart",
           "zenoh": f"zenoh://127.0.0.1:{helpers.free_udp_port()}/restart"}[scheme]
    first = server_thread(url)
    engine = helpers.RecordingEngine(rate_hz=100.0)
    rt = runner_thread(ClientRunner(engine, url, scene="floor", reconnect_delay_s=0.1, handshake_timeout_s=1.0,
                                    transport_options={"connect_timeout_s": 1.0} if scheme == "zenoh" else None))
    helpers.wait_for(lambda: len(first.updates) >= 5, what="updates to the first server")
    first.stop()  # Bye: the server is going away
    second = server_thread(url)
    helpers.wait_for(lambda: len(second.updates) >= 5, what="updates to the restarted server")
    rt.stop()
    assert rt.error is None
    st = rt.result
    assert st["sessions"] == 2 and st["sessions_ended"] >= 1
    assert second.updates[0].seq == 1  # a new session starts its sequence afresh
    # simulation time carried on: never backwards across the restart
    assert second.updates[0].env_time_s > first.updates[-1].env_time_s


def _silent_server(transport, stop, cfg):
    """A server loop that stops without Bye (a crash, a pulled cable)."""
    server = ServerEndpoint(transport.send, cfg)
    while not stop.is_set():
        now = time.monotonic_ns()
        for data, peer in transport.drain():
            up = server.receive(data, peer, now)
            if up is not None:
                server.send_proxy_state(up.session_id, now, np.array([0, 0, 0, 1.0, 0, 0, 0]), np.zeros(6), np.zeros(6))
        server.poll(now)
        time.sleep(0.001)
    return server


def test_survives_a_server_that_vanishes_and_reconnects_when_it_is_back(server_thread, runner_thread, helpers):
    port = helpers.free_udp_port()
    url = f"udp://127.0.0.1:{port}"
    cfg = ServerConfig(heartbeat_interval_s=0.05, silence_timeout_s=0.3)
    t = open_transport(url, role="server")
    stop = threading.Event()
    th = threading.Thread(target=_silent_server, args=(t, stop, cfg), daemon=True)
    th.start()
    engine = helpers.RecordingEngine(rate_hz=100.0)
    rt = runner_thread(ClientRunner(engine, url, scene="floor", reconnect_delay_s=0.1, handshake_timeout_s=0.3))
    try:
        helpers.wait_for(lambda: rt.runner.stats()["steps"] >= 5, what="a working session")
    finally:
        stop.set()
        th.join(5)
        t.close()  # gone, without a word
    helpers.wait_for(lambda: rt.runner.stats()["sessions_ended"] == 1, what="the silence timeout")
    steps_then = rt.runner.stats()["steps"]
    time.sleep(0.3)
    st = rt.runner.stats()
    assert rt.thread.is_alive() and rt.error is None
    assert st["state"] in ("waiting", "connecting", "handshaking") and st["steps"] == steps_then  # world paused
    assert st["end_reason"].startswith("server silent") or "no answer" in st["end_reason"]
    back = server_thread(url)
    helpers.wait_for(lambda: len(back.updates) >= 3, what="updates to the server that came back")
    rt.stop()
    assert rt.error is None and rt.result["sessions"] == 2


def test_without_reconnect_run_returns_when_the_server_goes_silent(helpers):
    url = "mem://silent-once"
    t = open_transport(url, role="server")
    stop = threading.Event()
    th = threading.Thread(target=_silent_server, args=(t, stop, ServerConfig(heartbeat_interval_s=0.05,
                                                                              silence_timeout_s=0.2)), daemon=True)
    th.start()
    engine = helpers.RecordingEngine(rate_hz=100.0)
    runner = ClientRunner(engine, url, scene="floor", reconnect=False)
    killer = threading.Timer(0.3, stop.set)
    killer.start()
    try:
        st = runner.run(duration_s=10.0)
    finally:
        stop.set()
        th.join(5)
        t.close()
    assert st["state"] == "stopped" and st["error"] is None
    assert st["end_reason"].startswith("server silent") and st["sessions"] == 1


def test_unreachable_server_gives_one_line_client_error(helpers):
    url = f"udp://127.0.0.1:{helpers.free_udp_port()}"  # nobody listens
    runner = ClientRunner(StubEngine(), url, scene="wall", connect_timeout_s=0.4, handshake_timeout_s=0.2)
    with pytest.raises(ClientError) as err:
        runner.run()
    msg = str(err.value)
    assert "\n" not in msg and url in msg and "0.4 s" in msg
    assert runner.stats()["state"] == "failed" and runner.stats()["hellos_sent"] >= 2


def test_missing_mem_server_is_retried_then_reported():
    runner = ClientRunner(StubEngine(), "mem://nobody-here", scene="wall", connect_timeout_s=0.3,
                          reconnect_delay_s=0.05)
    with pytest.raises(ClientError, match="no mem server"):
        runner.run()
    assert runner.stats()["transport_errors"] >= 2


def test_refused_tool_kind_raises_client_error(server_thread):
    srv = server_thread("mem://refuse", config=ServerConfig(supported_tools=frozenset({ToolKind.SPATIAL})))
    runner = ClientRunner(StubEngine(), srv.url, scene="wall", connect_timeout_s=5.0)
    with pytest.raises(ClientError, match="refused the session: UNSUPPORTED_TOOL"):
        runner.run()


def _rejecting_server(transport, stop):
    """Answers every Hello with Reject UNSUPPORTED_VERSION (a server of another major)."""
    codec = Codec()
    while not stop.is_set():
        for data, peer in transport.drain():
            msg = codec.try_decode(data)
            if isinstance(msg, Hello):
                transport.send(codec.encode(Reject(client_nonce=msg.client_nonce, code=ErrorCode.UNSUPPORTED_VERSION,
                                                   reason="server speaks 2.0 only", version_min=(2, 0),
                                                   version_max=(2, 0))), peer)
        time.sleep(0.001)


def test_version_refused_raises_client_error():
    t = open_transport("udp://127.0.0.1:0", role="server")
    stop = threading.Event()
    th = threading.Thread(target=_rejecting_server, args=(t, stop), daemon=True)
    th.start()
    try:
        runner = ClientRunner(StubEngine(), t.url, scene="wall", connect_timeout_s=5.0)
        with pytest.raises(ClientError) as err:
            runner.run()
    finally:
        stop.set()
        th.join(5)
        t.close()
    assert "UNSUPPORTED_VERSION" in str(err.value) and "2.0-2.0" in str(err.value)


def test_hmac_mode_talks_with_the_right_key_only(server_thread):
    srv = server_thread("mem://hmac", hmac_key=KEY)
    st = ClientRunner(StubEngine(), srv.url, scene="wall", hmac_key=KEY, realtime=False).run(max_steps=20)
    assert st["sessions"] == 1 and st["proxy_states"] > 0
    wrong = ClientRunner(StubEngine(), srv.url, scene="wall", hmac_key=bytes(32), connect_timeout_s=0.3)
    with pytest.raises(ClientError):
        wrong.run()


def test_runs_in_a_background_thread_and_reports_live_stats(server_thread, runner_thread, helpers):
    srv = server_thread("mem://background")
    engine = helpers.RecordingEngine(rate_hz=100.0)
    rt = runner_thread(ClientRunner(engine, srv.url, scene="floor"))
    helpers.wait_for(lambda: rt.runner.stats()["steps"] >= 3, what="steps")
    live = rt.runner.stats()
    assert live["state"] == "established" and live["sessions"] == 1
    helpers.wait_for(lambda: rt.runner.stats()["steps"] > live["steps"], what="more steps")
    rt.stop()
    assert rt.error is None and rt.result["state"] == "stopped"
    srv.wait_for_bye()


@pytest.mark.parametrize("kwargs, field", [
    ({"epsilon_m": -0.001}, "epsilon_m"), ({"epsilon_m": float("nan")}, "epsilon_m"),
    ({"max_contacts": 0}, "max_contacts"), ({"max_contacts": 65}, "max_contacts"),
    ({"reconnect_delay_s": 0}, "reconnect_delay_s"), ({"connect_timeout_s": -1.0}, "connect_timeout_s"),
])
def test_bad_arguments_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        ClientRunner(StubEngine(), "mem://x", scene="wall", **kwargs)


def test_bad_url_and_scene_are_refused_before_running():
    with pytest.raises(ValueError, match="scheme"):
        ClientRunner(StubEngine(), "tcp://127.0.0.1:1", scene="wall")
    with pytest.raises(ValueError, match="unknown scene 'moon'.*testbed"):
        ClientRunner(StubEngine(), "mem://x", scene="moon")
