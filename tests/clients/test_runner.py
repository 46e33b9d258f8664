"""The engine-neutral client loop against the protocol's reference server, a scripted server in
simulated time (``contract.ScriptedServer``: the protocol's ServerEndpoint on the in-memory
transport) and small fake servers where a test needs to misbehave on purpose: handshake, one
ContactUpdate per step, pacing, newest ProxyState, the server state (held while not rendered),
grants, heartbeats, reconnection, vanishing servers, refusals. Timing is simulated time or
counts, never the wall clock."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from hapticproxy.clients.contract import ProxyCommand, ScriptedServer, SimClock
from hapticproxy.clients.runner import ClientError, ClientRunner
from hapticproxy.clients.stub_engine import StubEngine
from hapticproxy.protocol.codec import Codec, Hello, ProxyState, Reject
from hapticproxy.protocol.messages import ErrorCode, ServerState, ToolKind
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


def _scripted(clock, script=None, **config):
    return ScriptedServer(clock, script or (lambda t, s: ProxyCommand(s.start_pose)),
                          config=ServerConfig(**config) if config else None)


def test_realtime_loop_keeps_pace_with_its_clock(helpers):
    """In simulated time: a 200 Hz engine run for 0.4 s steps every 5 ms of the runner's clock,
    never ahead of it."""
    clock = SimClock()
    srv = _scripted(clock)
    engine = helpers.RecordingEngine(rate_hz=200.0)
    runner = ClientRunner(engine, srv.url, scene="floor", clock_ns=clock, sleep=srv.sleep)
    t0 = clock()
    st = runner.run(duration_s=0.4)
    elapsed = (clock() - t0) / 1e9
    assert 78 <= st["steps"] <= 80  # 0.4 s at 200 Hz, less the handshake's first poll
    assert engine.time_s <= elapsed + 1e-12
    received = [t for t, _ in srv.updates]
    assert np.diff(received) == pytest.approx(0.005, abs=1e-9)  # one step per 5 ms of the clock


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


def test_heartbeats_keep_a_slow_engine_session_alive(helpers):
    clock = SimClock()
    srv = _scripted(clock, heartbeat_interval_s=0.05, silence_timeout_s=0.3)
    engine = helpers.RecordingEngine(rate_hz=2.0)  # a step every 0.5 s: longer than the silence timeout
    runner = ClientRunner(engine, srv.url, scene="floor", clock_ns=clock, sleep=srv.sleep)
    st = runner.run(duration_s=1.3)
    assert st["steps"] == 3  # at 0, 0.5 and 1.0 s
    assert st["heartbeats_sent"] >= 3 * 2  # twice at least in each 0.5 s between steps
    assert st["sessions"] == 1 and st["sessions_ended"] == 0
    assert srv.endpoint.counters.timeouts == 0 and srv.endpoint.counters.heartbeats_sent > 0


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
    attempts = rt.runner.stats()["connect_attempts"]
    helpers.wait_for(lambda: rt.runner.stats()["connect_attempts"] >= attempts + 2, what="two more attempts")
    st = rt.runner.stats()
    assert rt.thread.is_alive() and rt.error is None
    assert st["state"] in ("waiting", "connecting", "handshaking") and st["steps"] == steps_then  # world paused
    assert st["end_reason"].startswith("server silent") or "no answer" in st["end_reason"]
    back = server_thread(url)
    helpers.wait_for(lambda: len(back.updates) >= 3, what="updates to the server that came back")
    rt.stop()
    assert rt.error is None and rt.result["sessions"] == 2


def test_without_reconnect_run_returns_when_the_server_goes_silent(helpers):
    """In simulated time: the server stops answering at 0.3 s (no Bye); the runner gives the
    session up after the silence timeout it was told (0.2 s) and returns."""
    clock = SimClock()
    srv = _scripted(clock, heartbeat_interval_s=0.05, silence_timeout_s=0.2)
    t0 = clock()

    def sleep(s):
        clock.advance(s)
        if clock() - t0 < 0.3e9:
            srv.service()  # then it is gone, without a word

    engine = helpers.RecordingEngine(rate_hz=100.0)
    runner = ClientRunner(engine, srv.url, scene="floor", reconnect=False, clock_ns=clock, sleep=sleep)
    try:
        st = runner.run(duration_s=10.0)
    finally:
        srv.transport.close()
    assert st["state"] == "stopped" and st["error"] is None
    assert st["end_reason"].startswith("server silent") and st["sessions"] == 1
    # the last answer came within a step (10 ms) before 0.3 s; 0.2 s of silence later it gave up
    assert 0.3 - 0.011 + 0.2 <= (clock() - t0) / 1e9 <= 0.3 + 0.2 + 0.003


def test_unreachable_server_gives_one_line_client_error(helpers):
    url = f"udp://127.0.0.1:{helpers.free_udp_port()}"  # nobody listens
    clock = SimClock()
    runner = ClientRunner(StubEngine(), url, scene="wall", connect_timeout_s=0.4, handshake_timeout_s=0.2,
                          clock_ns=clock, sleep=clock.advance)
    with pytest.raises(ClientError) as err:
        runner.run()
    msg = str(err.value)
    assert "\n" not in msg and url in msg and "0.4 s" in msg
    # Hellos every 0.25 s of the runner's clock: at 0 and 0.25 s; then the handshake (0.2 s) is
    # given up and the transport reopened at once, Hello again
    st = runner.stats()
    assert st["state"] == "failed" and st["hellos_sent"] >= 2 and st["connect_attempts"] >= 2


def test_missing_mem_server_is_retried_then_reported():
    clock = SimClock()
    runner = ClientRunner(StubEngine(), "mem://nobody-here", scene="wall", connect_timeout_s=0.3,
                          reconnect_delay_s=0.05, clock_ns=clock, sleep=clock.advance)
    with pytest.raises(ClientError, match="no mem server"):
        runner.run()
    assert runner.stats()["transport_errors"] == 6  # at 0, 0.05, ..., 0.25 s: the 0.3 s deadline comes first


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
    # paced (30 steps at the engine's rate): unpaced, 20 steps could end before the server thread answered
    # on a loaded machine (seen once: no ProxyState)
    st = ClientRunner(StubEngine(), srv.url, scene="wall", hmac_key=KEY, realtime=True).run(max_steps=30)
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


# ------------------------------------------------------------------------------ server state
_SCHEDULE = ((0.2, ServerState.ENGAGED), (0.4, ServerState.FADING), (0.6, ServerState.ENGAGED),
             (0.8, ServerState.FAULT), (1.0, ServerState.IDLE), (1.2, ServerState.ENGAGED),
             (1.4, ServerState.UNKNOWN))


def _state_at(t):
    for end, state in _SCHEDULE:
        if t < end:
            return state
    return ServerState.UNKNOWN


def test_the_tool_follows_only_an_engaged_proxy_and_is_held_otherwise(helpers):
    """A scripted server (ServerEndpoint on the in-memory transport, simulated time) moves the proxy
    along +y at 0.1 m/s and reports engaged, fading, engaged, fault, idle, engaged, unknown: the
    engine is driven towards the proxy only while engaged (or unknown: a 1.1 server), is held at
    its own pose once when the server stops rendering, and follows the newest proxy at once when
    the server renders it again."""
    clock = SimClock()

    def script(t, s):
        pose = s.start_pose.copy()
        pose[1] = 0.1 * t
        twist = np.zeros(6)
        twist[1] = 0.1
        return ProxyCommand(pose, twist, server_state=_state_at(t))

    srv = _scripted(clock, script)
    engine = helpers.RecordingEngine(rate_hz=100.0)  # its tool jumps to where it is driven
    log = []
    runner = ClientRunner(engine, srv.url, scene="floor", clock_ns=clock, sleep=srv.sleep, log=log.append)
    st = runner.run(duration_s=1.6)
    ys = {round(t, 6): float(u.tool_pose[1]) for t, u in srv.updates}
    ts = sorted(ys)

    def tool_y(a, b):
        return [ys[t] for t in ts if a < t < b]

    # held: the tool stays where it was when the server stopped rendering (a step after 0.2 / 0.6 s)
    for a, b in ((0.2, 0.4), (0.6, 1.0)):
        held = tool_y(a + 0.02, b)
        assert held and max(held) - min(held) == 0.0, (a, b, held)
        assert min(held) < 0.1 * a + 0.002  # not where the proxy went meanwhile
    # engaged (and unknown): the tool is where the proxy was a step before
    for a, b in ((0.0, 0.2), (0.4, 0.6), (1.0, 1.2), (1.4, 1.6)):
        for t in ts:
            if a + 0.02 < t < b:
                assert ys[t] == pytest.approx(0.1 * t, abs=0.1 * 0.011), t
    assert st["holds"] == 2  # fading, then fault (idle after fault: still held, no second hold)
    assert st["proxy_held"] > 0 and st["proxy_applied"] > 0
    assert st["proxy_states"] == st["proxy_applied"] + st["proxy_held"] + st["proxy_superseded"]
    assert st["server_state"] == "unknown" and st["following"] is True
    assert any("holding the tool" in m for m in log) and any("following the proxy again" in m for m in log)
    # every drive was either a proxy pose (engaged) or the engine's own pose (held): never a pose
    # the proxy took while the server did not render it
    proxy_ys = {round(0.1 * t, 9) for t in ts}
    assert all(round(float(p[1]), 9) in proxy_ys or float(p[1]) in ys.values() for p in engine.driven)


def test_a_linkage_is_held_with_its_joints(helpers):
    """While not rendered, a linkage engine's joints are held at its own joint positions too."""
    from hapticproxy.clients.engine import LinkDescription, SceneInfo, ToolDescription

    class Chain(helpers.RecordingEngine):
        def __init__(self):
            super().__init__(rate_hz=100.0, n_contacts=0)
            self.joints = np.array([0.3, -0.2])
            self.joint_calls = []

        def load_scene(self, name):
            links = (LinkDescription(0.1), LinkDescription(0.1, parent=0, joint="revolute"),
                     LinkDescription(0.1, parent=1, joint="revolute"))
            return SceneInfo(name, ToolDescription("linkage", 0.3, links=links, held_link=2), env_rate_hz=100.0)

        def drive_joints(self, position, velocity, effort):
            self.joint_calls.append(np.array(position, dtype=float))
            if len(position):
                self.joints = np.array(position, dtype=float)

        def joint_positions(self, out):
            out[:] = self.joints
            return out

    clock = SimClock()

    def script(t, s):
        state = ServerState.FAULT if t >= 0.2 else ServerState.ENGAGED
        return ProxyCommand(s.start_pose, joint_position=np.array([1.0 + t, 2.0]), joint_velocity=np.zeros(2),
                            server_state=state)

    srv = _scripted(clock, script)
    engine = Chain()
    st = ClientRunner(engine, srv.url, scene="floor", clock_ns=clock, sleep=srv.sleep).run(duration_s=0.5)
    assert st["holds"] == 1 and st["proxy_held"] > 0
    # one call per engaged ProxyState, then the hold: the engine's own joints (where the last
    # engaged one put them), and nothing after it although the scripted joints moved on
    assert len(engine.joint_calls) == st["proxy_applied"] + 1
    np.testing.assert_array_equal(engine.joint_calls[-1], engine.joint_calls[-2])
    assert engine.joints[0] < 1.0 + 0.2 + 0.011


def test_start_up_time_does_not_count_against_the_connect_timeout(helpers):
    """An engine whose warm-up (compilation, a GUI coming up) takes 30 s of the runner's clock still
    gets its 5 s to connect: the timeout counts from the first attempt."""
    clock = SimClock()
    srv = _scripted(clock)

    class SlowStart(helpers.RecordingEngine):
        def warm_up(self):
            clock.advance(30.0)

    runner = ClientRunner(SlowStart(rate_hz=100.0), srv.url, scene="floor", connect_timeout_s=5.0, clock_ns=clock,
                          sleep=srv.sleep)
    st = runner.run(duration_s=0.2)
    assert st["error"] is None and st["sessions"] == 1 and st["steps"] >= 15


def test_the_servers_advice_moves_the_tools_target_ahead_and_its_epsilon_within_the_grant(helpers):
    """Protocol 1.2: a ProxyState's lead_s advances the pose the engine tracks along the proxy's
    twist (bounded by LEAD_MAX_S whatever the server says), and its epsilon_m re-inflates the
    tool only on a change above EPSILON_CHANGE_M and never above the granted epsilon."""
    from hapticproxy.clients import runner as R

    clock = SimClock()
    advice = [(0.2, 0.0, 0.0), (0.4, 0.05, 0.003), (0.6, 0.05, 0.0032), (0.8, 10.0, 0.5), (1.0, 0.0, 0.0)]

    def script(t, s):
        lead, eps = next(((lead, eps) for end, lead, eps in advice if t < end), (0.0, 0.0))
        twist = np.zeros(6)
        twist[1] = 0.1
        return ProxyCommand(s.start_pose.copy(), twist, lead_s=lead, epsilon_m=eps)

    srv = _scripted(clock, script)
    engine = helpers.RecordingEngine(rate_hz=100.0)
    runner = ClientRunner(engine, srv.url, scene="floor", epsilon_m=0.01, clock_ns=clock, sleep=srv.sleep)
    runner.run(duration_s=1.2)
    granted = runner.granted_epsilon_m
    y0 = float(srv.start_pose[1])
    ahead = sorted({round(float(p[1]) - y0, 9) for p in engine.driven})
    # no lead, a 50 ms lead at 0.1 m/s (5 mm ahead), and a 10 s lead cut to LEAD_MAX_S
    assert ahead == pytest.approx([0.0, 0.1 * 0.05, 0.1 * R.LEAD_MAX_S])
    # the grant first; the first advice re-inflates; 0.2 mm more does not; 0.5 m is cut to the
    # grant; no advice (0) is the grant (already there: no re-inflation)
    assert engine.eps_history[-3:] == pytest.approx([granted, 0.003, granted])
    assert engine.eps_history.count(0.003) == 1
    assert granted == pytest.approx(0.01)


def _ghost_hello() -> Hello:
    return Hello(client_nonce=99, tool_kind=ToolKind.PLANAR, mass_kg=0.2, inertia_kg_m2=(0.0, 0.0, 2e-4, 0.0, 0.0, 0.0),
                 engine="ghost", max_contacts=4, epsilon_m=0.005, env_rate_hz=60.0)


@pytest.mark.parametrize("had_a_session", [True, False])
def test_a_full_server_is_retried_after_a_first_session_and_refused_before(had_a_session):
    """A server restart can leave the slot to this client's own ghost: a Hello of an earlier
    attempt (another socket) that waited in the server's queue. After a first session the runner
    retries a full server (the ghost's session times out unheard) instead of giving up; before
    one, a full server is somebody else's and the runner says so."""
    from hapticproxy.protocol.session import ClientEndpoint

    clock = SimClock()
    srv = ScriptedServer(clock, lambda t, s: None, config=ServerConfig(max_sessions=1, silence_timeout_s=0.5))
    ghost_tr = open_transport(srv.url, role="client")
    ghost = ClientEndpoint(ghost_tr.send, _ghost_hello())
    runner = ClientRunner(StubEngine(), srv.url, scene="wall", realtime=False, reconnect_delay_s=0.1,
                          connect_timeout_s=5.0, clock_ns=clock, sleep=srv.sleep)
    try:
        def run_for(seconds):
            end = clock() + int(seconds * 1e9)
            while clock() < end:
                srv.sleep(runner.poll() or 0.001)

        if had_a_session:
            run_for(0.2)
            assert runner.stats()["sessions"] == 1 and srv.updates
            # the session ends (the server restarts); before the runner is back, the ghost's Hello
            # takes the only slot
            sid = next(iter(srv.endpoint.sessions))
            srv.endpoint.close(sid, now_ns=clock())
        ghost.start(clock())
        srv.service()
        assert len(srv.endpoint.sessions) == 1
        if not had_a_session:
            with pytest.raises(ClientError, match="refused the session: SERVER_FULL"):
                run_for(1.0)
            return
        n0 = len(srv.updates)
        run_for(2.0)
        st = runner.stats()
        assert st["error"] is None and st["state"] == "established"
        assert st["server_full"] >= 1 and st["sessions"] == 2
        assert len(srv.updates) > n0  # the second session's updates arrive
    finally:
        ghost_tr.close()
        runner.close()
        srv.close()


def test_a_client_without_its_server_says_so_every_connect_timeout(helpers):
    """Issue 32, papercut 7: in simulated time the server goes away without a word at 0.3 s; the
    runner ends the session after the silence timeout (0.2 s), says it is reconnecting, and then
    says it is still trying every connect_timeout_s (2 s), naming why, until it is stopped."""
    clock = SimClock()
    srv = _scripted(clock, heartbeat_interval_s=0.05, silence_timeout_s=0.2)
    t0 = clock()

    def sleep(s):
        clock.advance(s)
        if clock() - t0 < 0.3e9:
            srv.service()

    lines: list[tuple[float, str]] = []
    engine = helpers.RecordingEngine(rate_hz=100.0)
    runner = ClientRunner(engine, srv.url, scene="floor", connect_timeout_s=2.0, handshake_timeout_s=0.5,
                          clock_ns=clock, sleep=sleep, log=lambda m: lines.append(((clock() - t0) / 1e9, m)))
    try:
        st = runner.run(duration_s=7.0)
    finally:
        srv.transport.close()
    assert st["error"] is None and st["sessions"] == 1 and st["sessions_ended"] == 1
    ended = [t for t, m in lines if m.endswith("; reconnecting")]
    still = [(t, m) for t, m in lines if "still trying" in m]
    assert len(ended) == 1
    # one line 2 s, 4 s and 6 s after the session ended, and no more within 7 s
    assert [round(t - ended[0]) for t, _ in still] == [2, 4, 6], lines
    assert all(f"no session with {srv.url} for {k} s" in m for (_, m), k in zip(still, (2, 4, 6)))
    assert "no answer to Hello" in still[-1][1]


def test_the_clients_own_stall_is_counted_and_logged(helpers):
    """Issue 32, papercut 18: an engine step that keeps the client from sending for 200 ms is the
    client's stall: counted, its length kept, one line at once naming the advice; two more within
    5 s are one line later, with their count."""
    clock = SimClock()
    srv = _scripted(clock)
    t0 = clock()

    class Stalling(helpers.RecordingEngine):
        def step(self, dt_s):
            super().step(dt_s)
            if self.steps in (50, 60, 70, 700):   # 0.5 s, then twice within 5 s, then at 7 s
                clock.advance(0.2)

    lines: list[tuple[float, str]] = []
    runner = ClientRunner(Stalling(rate_hz=100.0), srv.url, scene="floor", clock_ns=clock, sleep=srv.sleep,
                          log=lambda m: lines.append(((clock() - t0) / 1e9, m)))
    st = runner.run(duration_s=8.5)
    assert st["stalls"] == 4, lines
    assert 200 <= st["stall_max_ms"] <= 215
    stalls = [m for _, m in lines if "client stalled" in m]
    assert len(stalls) == 2, stalls
    assert stalls[0].startswith("client stalled 2") and "lower priority" in stalls[0]
    assert stalls[1].startswith("client stalled 3 times since the last report")
