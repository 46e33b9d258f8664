"""Conformance kit for the remote-device link: ``hapticproxy protocol check-device | check-device-server``.

``check-device --server HOST:PORT`` plays a server driver on ``HOST:PORT`` and checks the device
program that streams to it (start the device with ``hapticproxy device --server HOST:PORT``, or
your own firmware); ``check-device-server --server HOST:PORT`` plays a device against the server
driver listening on ``HOST:PORT`` (e.g. ``hapticproxy serve`` with ``[device] driver =
"remote"`` and no environment client). Each is a scripted peer (libfranka's mock server is the
model): it runs the scenarios of SPEC.md's appendix "The remote-device link" against the peer
under test and judges what the peer does, then prints one line per rule (:data:`DEVICE_RULES`,
:data:`SERVER_RULES`): ``PASS`` with what was seen, or ``FAIL`` with why, and a ``RESULT`` line.
Exit status 0 if every rule passed, 1 if one failed, 2 on a usage or set-up error.

What is observable over the link decides how each rule is judged, and most rules need no clock:
a device echoes the seq of the last command it accepted (``STATE.cmd_seq``) and the key it is in,
so "the state that echoes this command is armed / disarmed" says exactly what the command did;
a server echoes the newest state seq it holds (``COMMAND.state_seq``), so a stale, malformed or
foreign STATE sent alone in one period shows whether it was taken. Only the two deadlines are
timed on the checker's clock: a device's watchdog (``watchdog_s`` + ``slack_s``) and a server's
reaction to link loss and to a device fault (``link_timeout_s`` + ``slack_s``, ``slack_s``).

Both checkers are stepped once per period (:meth:`_Scripted.step`) on an injectable clock over
any :class:`~hapticproxy.protocol.transport.Transport`, so a test can run them in lock-step with
the peer in simulated time; :meth:`_Scripted.run` paces them in real time for the CLI.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable

import numpy as np

from . import devlink as dl
from .devlink import COMMAND, F_ARMED, F_ENABLE, STATE, DeviceFault, DeviceKind

_NS = 1_000_000_000
#: how long a check waits for the peer to show the effect of one datagram (then it fails)
ECHO_TIMEOUT_S = 1.0
#: periods a "nothing may happen" check watches the peer for
WATCH_STATES = 30

DEVICE_RULES = {
    "state-stream": "STATE datagrams well formed: size, prefix, one device session, seq increasing, finite "
                    "pose/twist/time, unit quaternion, a known kind and fault",
    "starts-disarmed": "before any command the output is not armed and no key is echoed",
    "own-session": "commands addressed to another device session are ignored (armed or not)",
    "arms": "a newer key with the enable flag arms the output; the state echoes the key and cmd_seq",
    "newest-wins": "within a key, a stale or duplicate command (even a disable) changes nothing",
    "old-keys": "a command with an older key (older epoch, older server session) changes nothing",
    "disable": "an enable-clear command disarms the output at once, without a fault",
    "watchdog": "armed and no command: the output is cut within watchdog_s (+ slack), fault 2 (watchdog) reported",
    "rearm": "after a cut (disable, watchdog, non-finite), commands with the same key never re-arm; a newer key does",
    "non-finite": "a non-finite wrench is refused (output off, fault 1 reported); with a newer key it does not arm",
    "engagement": "the engagement counter starts the hand: the hand wrench is unchanged until the count rises, "
                  "then changes",
    "server-restart": "a newer server session (seq from 1) arms; commands of the older session are then ignored",
}

SERVER_RULES = {
    "commands": "COMMAND datagrams well formed, addressed to this device's session, seq increasing, key and "
                "engagements never going back, finite wrench, zero wrench when the enable flag is clear",
    "kind": "a device of another kind is never armed",
    "arms": "the server arms a device of its kind whose link is up (an enabled command)",
    "state-seq": "state_seq echoes the newest STATE: never ahead of what was sent, never back (a stale or "
                 "duplicate STATE is not taken)",
    "malformed-states": "a malformed STATE (size, magic, version, type, non-finite pose/time) is not taken",
    "state-v1": "a STATE of layout version 1 (216 bytes: an older device program, or a device without inputs) is "
                "taken",
    "foreign-states": "a STATE from another address is not taken and gets no command",
    "old-session": "a STATE of an older device session, while this one is alive, is ignored",
    "link-loss": "no STATE for longer than link_timeout_s: enable clear (+ slack); re-armed only with a newer key",
    "device-restart": "a restarted device (newer session, seq from 1): commands follow it, armed only with a newer key",
    "device-fault": "a fault the device reports under the server's key: enable clear within slack, that key "
                    "never enabled again",
}


class Report:
    """One verdict per rule: the first failure of a rule stays."""

    def __init__(self, rules: dict[str, str]) -> None:
        self.rules = rules
        self.results: dict[str, tuple[bool, str]] = {}

    def ok(self, rule: str, what: str = "") -> None:
        self._set(rule, True, what)

    def fail(self, rule: str, why: str) -> None:
        self._set(rule, False, why)

    def check(self, rule: str, ok: bool, what: str, why: str) -> bool:
        self._set(rule, ok, what if ok else why)
        return ok

    def _set(self, rule: str, ok: bool, text: str) -> None:
        if rule not in self.rules:
            raise KeyError(rule)
        if rule in self.results and not self.results[rule][0]:
            return
        if ok and rule in self.results:  # several passes: the first one says what was seen
            return
        self.results[rule] = (bool(ok), text)

    def fail_open(self, why: str) -> None:
        """Every rule without a verdict fails for ``why`` (the peer went silent, the run timed out)."""
        for rule in self.rules:
            if rule not in self.results:
                self.results[rule] = (False, why)

    @property
    def passed(self) -> bool:
        return all(self.results.get(r, (False, ""))[0] for r in self.rules)

    @property
    def failed(self) -> list[str]:
        return [r for r in self.rules if not self.results.get(r, (False, ""))[0]]

    def lines(self) -> list[str]:
        out = []
        for rule in self.rules:
            ok, text = self.results.get(rule, (False, "not reached"))
            out.append(f"{'PASS' if ok else 'FAIL'}  {rule:<17} {text}")
        n = len(self.rules)
        out.append(f"RESULT: PASS ({n} rules)" if self.passed else f"RESULT: FAIL ({len(self.failed)} of {n} rules)")
        return out


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.array_equal(a, b, equal_nan=True))


def _ms(ns: int) -> str:
    return f"{ns / 1e6:.0f} ms"


class _Scripted:
    """A scripted peer stepped once per period: receive everything waiting, advance the scenario
    (a generator; each ``yield`` waits one period), send this period's datagram."""

    rules: dict[str, str] = {}

    def __init__(self, transport, *, clock_ns: Callable[[], int] | None, period_s: float) -> None:
        self.tr = transport
        self.clock = clock_ns or time.monotonic_ns
        self.period_s = float(period_s)
        self.report = Report(self.rules)
        self.rx = bytearray(max(dl.MAX_DATAGRAM_BYTES, transport.max_packet_bytes))
        self.problem = ""
        self.done = False
        self._gen = self.script()

    def step(self) -> bool:
        """One period; returns ``False`` once the script has finished."""
        if self.done:
            return False
        now = self.clock()
        self.receive(now)
        try:
            next(self._gen)
        except StopIteration:
            self.done = True
        if not self.done:
            self.send(now)
        return not self.done

    def run(self, rate_hz: float, timeout_s: float = 120.0) -> Report:
        """Step at ``rate_hz`` in real time until the script ends (or ``timeout_s``)."""
        period = int(round(_NS / rate_hz))
        deadline = time.monotonic_ns()
        end = deadline + int(timeout_s * _NS)
        while self.step():
            deadline += period
            now = time.monotonic_ns()
            if now > end:
                self.report.fail_open(f"the check did not finish within {timeout_s:g} s")
                break
            if deadline > now:
                time.sleep((deadline - now) * 1e-9)
            elif now - deadline > 20 * period:
                deadline = now  # this process was held up: do not burst
        return self.report

    # -- scenario helpers (generators: ``ok = yield from self._until(...)``) -------------------
    def _until(self, pred: Callable[[], bool], timeout_s: float):
        end = self.clock() + int(timeout_s * _NS)
        while not pred():
            if self.clock() >= end:
                return False
            yield
        return True

    def _for(self, seconds: float):
        end = self.clock() + int(seconds * _NS)
        while self.clock() < end:
            yield

    def receive(self, now: int) -> None:
        """Everything waiting (at most MAX_DRAIN datagrams), each to :meth:`take`."""
        for _ in range(dl.MAX_DRAIN):
            n, peer = self.tr.recv_into(self.rx)
            if peer is None:
                return
            self.take(bytes(self.rx[:n]), peer, now)

    def _problem(self, text: str) -> None:
        """The first thing wrong with the peer's stream (its stream rule's reason)."""
        if not self.problem:
            self.problem = text

    # -- subclass hooks --------------------------------------------------------------------------
    def script(self):  # pragma: no cover - interface
        raise NotImplementedError
        yield

    def take(self, data: bytes, peer, now: int) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def send(self, now: int) -> None:  # pragma: no cover - interface
        raise NotImplementedError


# =============================================================================== check-device
class DeviceCheck(_Scripted):
    """Plays the server driver (a server-role transport) and checks the device that streams to it.

    ``watchdog_s``: the device's watchdog; ``slack_s``: how much later than that the cut may be
    seen (the device's tick, the network, both processes' scheduling); ``hand``: the device runs
    a scripted hand that starts at engagement (``False`` leaves the ``engagement`` rule out, for
    a real device in a user's hand); ``timeout_s``: how long to wait for the device's first STATE.
    """

    rules = DEVICE_RULES

    def __init__(self, transport, *, clock_ns=None, period_s: float = 1e-3, watchdog_s: float = dl.DEFAULT_WATCHDOG_S,
                 slack_s: float = 0.03, hand: bool = True, timeout_s: float = 30.0) -> None:
        if transport.role != "server":
            raise ValueError("transport: check-device plays the server: it needs a server-role transport")
        if not hand:
            self.rules = {k: v for k, v in DEVICE_RULES.items() if k != "engagement"}
        self.watchdog_s = float(watchdog_s)
        self.slack_s = float(slack_s)
        self.hand = bool(hand)
        self.timeout_s = float(timeout_s)
        super().__init__(transport, clock_ns=clock_ns, period_s=period_s)
        self.peer = None
        self.session = 0          # the device's session
        self.states: list[tuple[int, tuple]] = []   # (receive time ns, decoded STATE) of the device
        self.stream_gaps = 0
        self.foreign = 0
        self.plan: dict | None = None   # the command sent every period (None: send nothing)
        self._seq: dict[int, int] = {}  # server session -> last command seq used
        self.last_sent_ns = 0
        self.tx = COMMAND.new_buffer()
        self.tx_wrench = COMMAND.floats(self.tx)

    # -- the link ------------------------------------------------------------------------------
    @property
    def newest(self):
        return self.states[-1][1] if self.states else None

    def take(self, data: bytes, peer, now: int) -> None:
        if self.peer is None:
            self.peer = peer
        elif peer != self.peer:
            self.foreign += 1
            return
        try:
            s = dl.unpack_state(data)  # either layout (version 1: a device without inputs)
        except ValueError as exc:
            self._problem(str(exc))
            return
        if self.session == 0:
            self.session = s.device_session
        elif s.device_session != self.session:
            self._problem(f"device_session changed from {self.session} to {s.device_session}")
            return
        last = self.newest
        if last is not None and s.seq <= last.seq:
            self._problem(f"seq went from {last.seq} to {s.seq}")
            return
        if last is not None and s.seq > last.seq + 1:
            self.stream_gaps += s.seq - last.seq - 1
        if last is None and s.seq != 1:
            self.stream_gaps += s.seq - 1
        if not dl.row_finite(s.state):
            self._problem(f"non-finite pose, twist or time in state seq {s.seq}")
            return
        q = s.state[3:7]
        if abs(float(np.dot(q, q)) - 1.0) > 2e-6:
            self._problem(f"quaternion not unit in state seq {s.seq}")
        if s.kind not in DeviceKind.__members__.values() or s.fault not in DeviceFault.__members__.values():
            self._problem(f"unknown kind {s.kind} or fault {s.fault} in state seq {s.seq}")
        if s.period_us == 0:
            self._problem("period_us is 0")
        self.states.append((now, s))

    def next_seq(self, server_session: int) -> int:
        self._seq[server_session] = self._seq.get(server_session, 0) + 1
        return self._seq[server_session]

    def command(self, *, key, enable: bool, wrench=None, engagements: int = 0, to: int | None = None,
                seq: int | None = None) -> int:
        """Send one COMMAND now (``seq`` None: the key's next seq); returns its seq."""
        if seq is None:
            seq = self.next_seq(key[0])
        w = self.tx_wrench
        w[:] = 0.0 if wrench is None else wrench
        COMMAND.body.pack_into(self.tx, dl.PREFIX_BYTES, F_ENABLE if enable else 0,
                               self.session if to is None else to, key[0], key[1], engagements, seq,
                               self.newest.seq if self.states else 0)
        if self.peer is not None:
            self.tr.send(self.tx, self.peer)
            self.last_sent_ns = self.clock()
        return seq

    def send(self, now: int) -> None:
        p = self.plan
        if p is not None and self.peer is not None:
            p["last_seq"] = self.command(key=p["key"], enable=p["enable"], wrench=p.get("wrench"),
                                         engagements=p.get("engagements", 0), to=p.get("to"))
            p.setdefault("first_seq", p["last_seq"])

    def feed(self, key, enable=True, *, wrench=None, engagements=0, to=None) -> dict:
        self.plan = dict(key=key, enable=enable, wrench=wrench, engagements=engagements, to=to)
        return self.plan

    # -- observations ----------------------------------------------------------------------------
    def _since(self, t_ns: int):
        return [s for t, s in self.states if t > t_ns]

    def _echo(self, key, seq: int):
        """The first state of the newest run of states that echo a command of ``key`` with a seq
        >= ``seq`` (the device's echoes only grow), or None."""
        first = None
        for _, s in reversed(self.states):
            if (s.server_session, s.epoch) != key or s.cmd_seq < seq:
                break
            first = s
        return first

    def _wait_echo(self, key, seq: int):
        """Wait (sending the plan) until a state echoes ``(key, seq)``; that state or None."""
        got = yield from self._until(lambda: self._echo(key, seq) is not None, ECHO_TIMEOUT_S)
        return self._echo(key, seq) if got else None

    def _states(self, n: int):
        """Wait for ``n`` more states (at most ECHO_TIMEOUT_S + n periods)."""
        want = len(self.states) + n
        return (yield from self._until(lambda: len(self.states) >= want, ECHO_TIMEOUT_S + n * self.period_s))

    def _arm(self, key, rule: str, *, engagements: int = 0):
        """Feed ``key`` with the enable flag until the device echoes it armed; the state or None."""
        p = self.feed(key, engagements=engagements)
        yield
        s = yield from self._wait_echo(key, p["first_seq"])
        if s is None:
            self.report.fail(rule, f"no state echoed the command key {key} within {ECHO_TIMEOUT_S:g} s")
        elif not s.flags & F_ARMED:
            self.report.fail(rule, f"a command of the newer key {key} with the enable flag did not arm "
                                   f"(fault {s.fault})")
            return None
        return s

    # -- the scenario ----------------------------------------------------------------------------
    def _stream_verdict(self) -> None:
        if self.states:
            self.report.check("state-stream", not self.problem,
                              f"{len(self.states)} states" + (f", {self.stream_gaps} lost" if self.stream_gaps else ""),
                              self.problem)

    def script(self):
        yield from self._script()
        self._stream_verdict()

    def _script(self):
        R = self.report
        got = yield from self._until(lambda: self.newest is not None, self.timeout_s)
        if not got:
            R.fail_open(f"no STATE from a device within {self.timeout_s:g} s")
            return
        got = yield from self._states(20)
        if not got:
            self._stream_verdict()
            R.fail_open("the device stopped streaming")
            return
        if any(s.flags & F_ARMED or (s.server_session, s.epoch) != (0, 0) for _, s in self.states):
            R.fail("starts-disarmed", "armed, or echoing a key, before any command")
        else:
            R.ok("starts-disarmed", f"{len(self.states)} states, not armed, no key")
        hand0 = self.newest.state[13:19].copy()
        S = dl.new_session()

        # own-session: enabled commands for another boot of the device
        t0 = self.clock()
        self.feed((S, 1), to=self.session + 1)
        yield from self._states(WATCH_STATES)
        self.plan = None
        bad = [s for s in self._since(t0) if s.flags & F_ARMED or (s.server_session, s.epoch) == (S, 1)]
        if bad:
            R.fail("own-session", "a command addressed to another device session armed it")

        # arms
        s = yield from self._arm((S, 1), "arms")
        if s is None:
            self._stream_verdict()
            R.fail_open("not reached: the device could not be armed")
            return
        R.ok("arms", f"armed by the first command of a new key, cmd_seq {s.cmd_seq} echoed")
        self.K = (S, 1)

        # newest-wins: a stale and a duplicate disable within the key
        n = self.plan["last_seq"]
        ok = yield from self._unmoved([dict(key=self.K, enable=False, seq=max(1, n - 5)),
                                       dict(key=self.K, enable=False, seq=n)])
        R.check("newest-wins", ok, "a stale and a duplicate disable left it armed",
                "a stale or duplicate disable disarmed it" if ok is False else "no state echoed the next command")
        yield from self._recover()

        # old-keys: disables under an older epoch and an older server session
        ok = yield from self._unmoved([dict(key=(self.K[0], 0), enable=False, seq=10 ** 6),
                                       dict(key=(self.K[0] - 1, 7), enable=False, seq=10 ** 6)])
        R.check("old-keys", ok, "disables with an older epoch and an older server session were ignored",
                "a command with an older key was obeyed" if ok is False else "no state echoed the next command")
        yield from self._recover()

        # own-session while armed: a disable for another boot of the device
        ok = yield from self._unmoved([dict(key=self.K, enable=False, to=self.session + 1)])
        R.check("own-session", ok, "commands for another device session ignored, unarmed and armed",
                "a disable addressed to another device session disarmed it" if ok is False else
                "no state echoed the next command")
        yield from self._recover()

        # disable, and the same key does not re-arm
        self.plan = None
        seq = self.command(key=self.K, enable=False)
        yield
        s = yield from self._wait_echo(self.K, seq)
        if s is None:
            R.fail("disable", "no state echoed the disable command")
        elif R.check("disable", not s.flags & F_ARMED and s.fault == 0,
                     "disarmed by the state that echoes the disable, no fault",
                     "still armed in the state that echoes the disable" if s.flags & F_ARMED else
                     f"disarmed with fault {s.fault} instead of none"):
            yield from self._same_key_stays_off("disable")
        if (yield from self._recover(always=True, rule="rearm")):
            R.ok("rearm", "after a cut the same key did not re-arm and a newer key did")

        # watchdog: stop commanding an armed device
        self.plan = None
        t_last = self.last_sent_ns
        limit = int((self.watchdog_s + self.slack_s) * _NS)
        got = yield from self._until(lambda: not self.newest.flags & F_ARMED, self.watchdog_s + self.slack_s + 1.0)
        if not got:
            R.fail("watchdog", f"still armed {_ms(self.clock() - t_last)} after the last command")
        else:
            # the cut: the first disarmed state after the last armed one, in the device's order
            # (one read can bring a state the device sent before it took the command that armed
            # it, next to the state that echoes that command: not the cut)
            armed = max((i for i, (_, x) in enumerate(self.states) if x.flags & F_ARMED), default=-1)
            t_cut, s = next((t, x) for t, x in self.states[armed + 1:] if not x.flags & F_ARMED)
            dt = t_cut - t_last
            if dt > limit:
                R.fail("watchdog", f"cut {_ms(dt)} after the last command (watchdog_s {self.watchdog_s:g} + slack "
                                   f"{self.slack_s:g})")
            elif s.fault != DeviceFault.WATCHDOG:
                R.fail("watchdog", f"cut after {_ms(dt)} but reported fault {s.fault}, not 2 (watchdog)")
            else:
                R.ok("watchdog", f"cut {_ms(dt)} after the last command, fault 2 reported")
            yield from self._same_key_stays_off("watchdog")
        yield from self._recover(always=True, rule="rearm")

        # non-finite: refused and latched; with a newer key it does not arm
        self.plan = None
        seq = self.command(key=self.K, enable=True, wrench=[math.nan, 0, 0, 0, 0, 0])
        yield
        s = yield from self._wait_echo(self.K, seq)
        if s is None or s.flags & F_ARMED or s.fault != DeviceFault.NONFINITE_COMMAND:
            R.fail("non-finite", "no state echoed the non-finite command" if s is None else
                   "still armed after a non-finite wrench" if s.flags & F_ARMED else
                   f"disarmed but reported fault {s.fault}, not 1 (non-finite command)")
        else:
            yield from self._same_key_stays_off("non-finite")
        yield from self._recover(always=True, rule="rearm")
        self.K = (self.K[0], self.K[1] + 1)
        t0 = self.clock()
        p = self.feed(self.K, wrench=[0, 0, math.inf, 0, 0, 0])
        yield
        s = yield from self._wait_echo(self.K, p["first_seq"])
        # (armed under the new key: a state of the old key still in flight at t0 may be armed)
        if s is None or any(x.flags & F_ARMED and (x.server_session, x.epoch) == self.K for x in self._since(t0)):
            R.fail("non-finite", "no state echoed a non-finite command of a newer key" if s is None else
                   "a non-finite command of a newer key armed it")
        else:
            R.ok("non-finite", "refused and reported (fault 1); a newer key with a non-finite wrench did not arm")
        if not (yield from self._recover(always=True, rule="arms")):
            self._stream_verdict()
            R.fail_open("not reached: the device could not be re-armed")
            return

        # engagement: the hand waits for the count to rise
        if self.hand:
            if not all(_same(x.state[13:19], hand0) for _, x in self.states):
                R.fail("engagement", "the hand wrench changed before any engagement")
            else:
                t0 = self.clock()
                self.feed(self.K, engagements=1)
                got = yield from self._until(lambda: not _same(self.newest.state[13:19], hand0), ECHO_TIMEOUT_S)
                if not got:
                    R.fail("engagement", f"the hand wrench did not change within {ECHO_TIMEOUT_S:g} s of the count "
                                         "rising (run the device with a scripted hand, or use --no-hand)")
                else:
                    t1 = next(t for t, x in self.states if t > t0 and not _same(x.state[13:19], hand0))
                    R.ok("engagement", f"the hand started {_ms(t1 - t0)} after the count rose")

        # server-restart: a newer session, seq from 1; the older one is then ignored
        S = self.K[0]
        self.K = K2 = (dl.new_session(), 1)
        if (yield from self._arm(K2, "server-restart")) is not None:
            ok = yield from self._unmoved([dict(key=(S, 99), enable=False, seq=10 ** 6)])
            R.check("server-restart", ok, "armed by the newer session's first command; the older session's disable "
                                          "ignored",
                    "a command of the older server session was obeyed" if ok is False else
                    "no state echoed the next command")
        # leave it disarmed
        self.plan = None
        seq = self.command(key=self.K, enable=False)
        yield
        yield from self._wait_echo(self.K, seq)

    def _unmoved(self, crafted: list[dict]):
        """Send ``crafted`` commands to the armed device, then the current key's next command:
        True if every state until that command's echo stayed armed under the current key, False
        if not, None if no state echoed it."""
        self.plan = None
        t0 = self.clock()
        for c in crafted:
            self.command(**c)
        yield
        p = self.feed(self.K)
        yield
        s = yield from self._wait_echo(self.K, p["first_seq"])
        if s is None:
            return None
        return all(x.flags & F_ARMED and (x.server_session, x.epoch) == self.K for x in self._since(t0))

    def _recover(self, *, always: bool = False, rule: str = "arms"):
        """Go on from a known state: arm with a newer key (if not armed under the current key, or
        ``always``); True if armed."""
        s = self.newest
        dev_key = (s.server_session, s.epoch)
        if not always and s.flags & F_ARMED and dev_key == self.K:
            return True
        if dev_key > self.K:  # the device took a key this checker did not mean: go past it
            self.K = (dl.new_session(), 1)
        else:
            self.K = (self.K[0], self.K[1] + 1)
        return (yield from self._arm(self.K, rule)) is not None

    def _same_key_stays_off(self, cause: str):
        """After a cut: commands of the same key with the enable flag never re-arm (rule rearm)."""
        key = self.K
        t0 = self.clock()
        p = self.feed(key)
        yield
        s = yield from self._wait_echo(key, p["first_seq"])
        yield from self._states(WATCH_STATES)
        if any(x.flags & F_ARMED for x in self._since(t0)):
            self.report.fail("rearm", f"after the {cause} cut a command of the same key re-armed it")
        elif s is None:
            self.report.fail("rearm", f"after the {cause} cut no state echoed a command of the same key")
        self.plan = None


# ======================================================================== check-device-server
class ServerCheck(_Scripted):
    """Plays a device (a client-role transport to the server driver) and checks the server.

    ``kind``: the server driver's device kind; ``link_timeout_s``: its link timeout;
    ``slack_s``: how much later than a deadline the server's reaction may be seen;
    ``arm_timeout_s``: how long to wait for the server to arm; ``reopen``: a callable returning
    another client transport to the same server (for the foreign-address rule; ``None``: that
    rule fails as not checkable).
    """

    rules = SERVER_RULES

    def __init__(self, transport, *, kind: str = "planar", clock_ns=None, period_s: float = 1e-3,
                 link_timeout_s: float = dl.DEFAULT_LINK_TIMEOUT_S, slack_s: float = 0.05,
                 arm_timeout_s: float = 5.0, reopen: Callable[[], object] | None = None) -> None:
        if transport.role != "client":
            raise ValueError("transport: check-device-server plays the device: it needs a client-role transport")
        if kind not in dl.KINDS_BY_NAME:
            raise ValueError(f"kind: expected one of {', '.join(dl.KINDS_BY_NAME)}, got {kind!r}")
        self.kind = int(dl.KINDS_BY_NAME[kind])
        self.link_timeout_s = float(link_timeout_s)
        self.slack_s = float(slack_s)
        self.arm_timeout_s = float(arm_timeout_s)
        self.reopen = reopen
        super().__init__(transport, clock_ns=clock_ns, period_s=period_s)
        self.session = dl.new_session()
        self.sessions = {self.session}
        self.seq = 0
        self.max_sent_seq = 0
        self.send_kind = self.kind
        self.fault = 0
        self.silent = False
        self.skip = 0                # periods without a regular STATE (a crafted one went instead)
        # the device this checker plays: newest key, cmd_seq, armed (a correct device's rules)
        self.key = (0, 0)
        self.cmd_seq = 0
        self.armed = False
        self.cmds: list[tuple[int, tuple]] = []   # (receive time ns, decoded COMMAND)
        self._last: dict[int, tuple] = {}         # server session -> last command
        self.tx = STATE.new_buffer()
        self.row = STATE.floats(self.tx)
        self.row[:] = 0.0
        self.row[3] = 1.0
        self.row[13:19] = math.nan

    # -- the link ------------------------------------------------------------------------------
    def take(self, data: bytes, peer, now: int) -> None:
        try:
            c = COMMAND.unpack(data)
        except ValueError as exc:
            self._problem(str(exc))
            return
        if c.device_session not in self.sessions:
            self._problem(f"a command addressed to device session {c.device_session}, not one of this device's")
            return
        if not np.isfinite(c.wrench).all():
            self._problem(f"a non-finite wrench in command seq {c.seq}")
        if not c.flags & F_ENABLE and np.any(c.wrench != 0.0):
            self._problem(f"a non-zero wrench with the enable flag clear (seq {c.seq})")
        last = self._last.get(c.server_session)
        if last is not None:
            if c.seq <= last.seq:
                self._problem(f"command seq went from {last.seq} to {c.seq}")
            if c.epoch < last.epoch:
                self._problem(f"epoch went back from {last.epoch} to {c.epoch}")
            if c.engagements < last.engagements and last.engagements - c.engagements < 1 << 31:
                self._problem(f"engagements went back from {last.engagements} to {c.engagements}")
        if self._last and c.server_session < max(self._last):
            self._problem("a command of an older server session after a newer one")
        self._last[c.server_session] = c
        self.cmds.append((now, c))
        # a correct device's rules: its own session, newest key, newest seq, latched cuts
        if c.device_session != self.session:
            return
        key = (c.server_session, c.epoch)
        if key < self.key:
            return
        enable = bool(c.flags & F_ENABLE) and bool(np.isfinite(c.wrench).all())
        if key > self.key:  # a newer key clears a latched fault; with the enable flag it arms
            self.key, self.cmd_seq = key, c.seq
            self.fault = 0
            self.armed = enable
            return
        if c.seq <= self.cmd_seq:
            return
        self.cmd_seq = c.seq
        if not enable:
            self.armed = False

    def state(self, *, seq: int, session: int | None = None, tr=None, row=None) -> None:
        """Send one STATE now: this device's fields and state row (or ``row``), ``seq``, ``session``."""
        self.row[19] = self.clock() * 1e-9
        buf = self.tx
        if row is not None:
            buf = bytearray(self.tx)
            STATE.floats(buf)[:19] = row[:19]
        STATE.body.pack_into(buf, dl.PREFIX_BYTES, F_ARMED if self.armed else 0,
                             self.session if session is None else session, self.key[0], self.key[1],
                             int(round(self.period_s * 1e6)), seq, self.cmd_seq, self.send_kind, self.fault)
        (tr or self.tr).send(buf)

    def send(self, now: int) -> None:
        if self.silent:
            return
        if self.skip:
            self.skip -= 1
            return
        self.seq += 1
        self.max_sent_seq = max(self.max_sent_seq, self.seq)
        self.state(seq=self.seq)

    # -- observations ----------------------------------------------------------------------------
    def _since(self, t_ns: int):
        return [c for t, c in self.cmds if t > t_ns]

    def _enabled_since(self, t_ns: int, session: int | None = None):
        sess = self.session if session is None else session
        return [c for c in self._since(t_ns) if c.flags & F_ENABLE and c.device_session == sess]

    def _wait_enabled(self, t_ns: int):
        """Wait until the server sends an enabled command to this device's session: the time
        (ns after ``t_ns``) and the command, or None (after ``arm_timeout_s``)."""
        def hit():
            return next(((t, c) for t, c in self.cmds if t > t_ns and c.flags & F_ENABLE
                         and c.device_session == self.session), None)
        got = yield from self._until(lambda: hit() is not None, self.arm_timeout_s)
        if not got:
            return None
        t, c = hit()
        return t - t_ns, c

    def _alone(self, *, raw: bytes | None = None, tr=None, **fields):
        """Send one crafted STATE (or ``raw`` bytes) with no regular STATE for two periods, so the
        server's next commands show whether it took it; returns the commands of those periods."""
        t0 = self.clock()
        self.skip = 2
        if raw is not None:
            (tr or self.tr).send(raw)
        else:
            self.state(tr=tr, **fields)
        for _ in range(3):
            yield
        return self._since(t0)

    # -- the scenario ----------------------------------------------------------------------------
    def _script(self):
        R = self.report
        # kind: states of another kind first; the server must not arm
        self.send_kind = (self.kind + 1) % 3
        got = yield from self._until(lambda: bool(self.cmds), self.arm_timeout_s)
        if not got:
            R.fail_open(f"no command from the server within {self.arm_timeout_s:g} s")
            return
        t0 = self.clock()
        yield from self._for(max(0.3, 3 * self.link_timeout_s))
        R.check("kind", not self._enabled_since(t0),
                f"not armed while a device of kind {self.send_kind} streamed ({len(self._since(t0))} commands)",
                f"armed a device of kind {self.send_kind}")
        self.send_kind = self.kind
        t0 = self.clock()
        got = yield from self._wait_enabled(t0)
        if got is None:
            self._commands_verdict()
            R.fail_open(f"the server did not arm the device within {self.arm_timeout_s:g} s (a server that heard "
                        "the wrong kind before it ran may hold a fault: start the check once it runs)")
            return
        R.ok("arms", f"armed {_ms(got[0])} after the device of its kind streamed")
        yield from self._for(0.05)

        # state-seq: a stale and a duplicate STATE, each alone in its period
        cur = self.seq
        seen = yield from self._alone(seq=max(1, cur - 5), row=self._pose(0.01))
        seen += yield from self._alone(seq=self.seq, row=self._pose(0.02))   # the newest again
        if any(c.state_seq < cur for c in seen):
            R.fail("state-seq", "a stale STATE was taken (state_seq went back)")

        # malformed-states: each as the next seq, alone; a correct server never echoes it
        bad = {}
        for what, fields in (("long", dict(extra=1)), ("magic", dict(magic=b"XXXX")),
                             ("version", dict(version=dl.VERSION + 1)), ("type", dict(type_id=2)),
                             ("NaN pose", dict(nan=0)), ("NaN time", dict(nan=19)), ("NaN twist", dict(nan=8))):
            self.seq += 1
            crafted = self.seq
            seen = yield from self._alone(raw=self._malformed(crafted, **fields))
            if any(c.state_seq == crafted for c in seen):
                bad[what] = True
        # (a version-1 STATE with version 2's byte, and a version-2 size with version 1's, are neither layout)
        for what, fields in (("version 2 at 216 bytes", dict(version=dl.STATE.version, v1=True)),
                             ("version 1 at 240 bytes", dict(version=dl.STATE_V1.version))):
            self.seq += 1
            crafted = self.seq
            seen = yield from self._alone(raw=self._malformed(crafted, **fields))
            if any(c.state_seq == crafted for c in seen):
                bad[what] = True
        R.check("malformed-states", not bad, "9 kinds of malformed STATE (size, magic, version, type, NaN) not taken",
                "taken: " + ", ".join(bad))
        # state-v1: the layout an older device program sends, as the next seq, alone
        self.seq += 1
        crafted = self.seq
        seen = yield from self._alone(raw=self._malformed(crafted, v1=True))
        R.check("state-v1", any(c.state_seq == crafted for c in seen), "a version-1 STATE was taken",
                "a version-1 STATE (216 bytes) was not taken")
        enabled_after = yield from self._wait_enabled(self.clock())
        if enabled_after is None:
            R.fail("malformed-states", "the server stopped arming the device after malformed states")

        # foreign-states: the same session from another address
        if self.reopen is None:
            R.fail("foreign-states", "not checkable: no second transport to send from")
        else:
            other = self.reopen()
            try:
                self.seq += 1
                crafted = self.seq
                seen = yield from self._alone(seq=crafted, tr=other)
                buf = bytearray(other.max_packet_bytes)
                got_other = 0
                while other.recv_into(buf)[1] is not None:
                    got_other += 1
            finally:
                other.close()
            R.check("foreign-states", not got_other and not any(c.state_seq == crafted for c in seen),
                    "a STATE from another address was not taken and got no command",
                    "the other address got commands" if got_other else "a STATE from another address was taken")

        # old-session: an older boot of this device while it is alive
        self.sessions.add(self.session - 1)  # a wrong server's commands to it are judged here, not in "commands"
        t0 = self.clock()
        yield from self._alone(seq=1, session=self.session - 1)
        yield from self._for(0.05)
        seen = self._since(t0)
        R.check("old-session", bool(seen) and all(c.device_session == self.session for c in seen)
                and any(c.flags & F_ENABLE for c in seen[-5:]),
                "ignored: commands stayed with the live session, armed",
                "commands went to the older session" if any(c.device_session != self.session for c in seen) else
                "the server disarmed the live device")
        R.check("state-seq", all(c.state_seq <= self.max_sent_seq for _, c in self.cmds),
                f"echoed the newest of {self.max_sent_seq} states, a stale and a duplicate one not taken",
                "state_seq ahead of every STATE sent")

        # link-loss: silence longer than the server's link timeout
        en = self._enabled_since(0)
        k_before = (en[-1].server_session, en[-1].epoch) if en else (0, 0)
        self.silent = True
        t_silent = self.clock()
        silence_s = max(0.5, 3 * self.link_timeout_s)
        yield from self._for(silence_s)
        limit = t_silent + int((self.link_timeout_s + self.slack_s) * _NS)
        late = [t for t, c in self.cmds if t >= limit and c.flags & F_ENABLE]
        self.silent = False
        t_back = self.clock()
        got = yield from self._wait_enabled(t_back)
        stale_key = [x for x in self._enabled_since(t_back) if (x.server_session, x.epoch) <= k_before]
        if late:
            R.fail("link-loss", f"still enabled {_ms(late[-1] - t_silent)} into a silence "
                                f"(link_timeout_s {self.link_timeout_s:g} + slack {self.slack_s:g})")
        elif stale_key:
            R.fail("link-loss", "re-armed with the key from before the link loss")
        elif got is None:
            R.ok("link-loss", "enable cleared by the link timeout; not re-armed")
            self._commands_verdict()
            R.fail_open(f"the server did not re-arm within {self.arm_timeout_s:g} s after the link came back "
                        "(it must arm a device whose link is up before its first engagement)")
            return
        else:
            R.ok("link-loss", f"enable cleared by the link timeout; re-armed with a newer key {_ms(got[0])} "
                              "after the link came back")

        # device-restart: a newer session, seq from 1, from the same address
        en = self._enabled_since(0)
        k_before = (en[-1].server_session, en[-1].epoch)
        old = self.session
        self.session = dl.new_session()
        self.sessions.add(self.session)
        self.seq = 0
        self.key, self.cmd_seq, self.armed = (0, 0), 0, False
        t_restart = self.clock()
        got = yield from self._wait_enabled(t_restart)
        followed = [x for x in self._since(t_restart) if x.device_session == self.session]
        stale_key = [x for x in self._enabled_since(t_restart) if (x.server_session, x.epoch) <= k_before]
        if not followed:
            R.fail("device-restart", "no command was addressed to the restarted device")
        elif stale_key:
            R.fail("device-restart", "armed the restarted device with the key from before the restart")
        elif got is None:
            R.ok("device-restart", "followed the restarted device, not re-armed")
            self._commands_verdict()
            R.fail_open(f"the server did not re-arm the restarted device within {self.arm_timeout_s:g} s")
            return
        else:
            late = [x for x in self._since(t_restart + int(self.slack_s * _NS)) if x.device_session == old]
            R.check("device-restart", not late, "commands followed the new session; armed with a newer key",
                    f"commands still went to the old session {self.slack_s:g} s after the restart")
        yield from self._for(0.05)

        # device-fault: the device reports its watchdog fault under the server's key
        yield from self._until(lambda: self.armed, 1.0)
        k = self.key
        self.fault = int(DeviceFault.WATCHDOG)
        self.armed = False
        t_fault = self.clock()
        yield from self._for(max(0.3, 3 * self.link_timeout_s))
        limit = t_fault + int(self.slack_s * _NS)
        late = [c for t, c in self.cmds if t >= limit and c.flags & F_ENABLE and (c.server_session, c.epoch) <= k
                and c.device_session == self.session]
        R.check("device-fault", not late and bool(self._since(limit)),
                "enable cleared after the device reported its watchdog fault; that key not enabled again",
                "still enabled under the faulted key" if late else "no command after the fault report")

    def _commands_verdict(self) -> None:
        if self.cmds:
            self.report.check("commands", not self.problem, f"{len(self.cmds)} commands", self.problem)

    def script(self):
        yield from self._script()
        self._commands_verdict()

    def _pose(self, x: float) -> np.ndarray:
        row = np.array(self.row)
        row[0] = x
        return row

    def _malformed(self, seq: int, *, extra: int = 0, magic: bytes | None = None, version: int | None = None,
                   type_id: int | None = None, nan: int | None = None, v1: bool = False) -> bytes:
        """A STATE as this device would send it, then spoilt as asked (``v1``: in layout version
        1, which is not spoilt by itself)."""
        layout = dl.STATE_V1 if v1 else STATE
        row = np.array(self.row[:layout.block.count])
        if nan is not None:
            row[nan] = math.nan
        data = bytearray(layout.pack(flags=F_ARMED if self.armed else 0, device_session=self.session,
                                     server_session=self.key[0], epoch=self.key[1],
                                     period_us=int(round(self.period_s * 1e6)), seq=seq, cmd_seq=self.cmd_seq,
                                     kind=self.kind, fault=self.fault, state=row))
        if magic is not None:
            data[0:4] = magic
        if version is not None:
            data[4] = version
        if type_id is not None:
            data[5] = type_id
        return bytes(data) + bytes(extra)


# ------------------------------------------------------------------------------------ CLI
def _hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise ValueError(f"--server: expected HOST:PORT, got {text!r}")
    return host, int(port)


def _positive(name: str, v: float, lo: float = 0.0, hi: float = 3600.0) -> float:
    if not (math.isfinite(v) and lo < v <= hi):
        raise ValueError(f"{name}: expected a number in ({lo:g}, {hi:g}], got {v:g}")
    return v


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hapticproxy protocol", description="Remote-device link conformance kit.")
    sub = parser.add_subparsers(dest="mode", required=True)
    pd = sub.add_parser("check-device", help="play a server driver and check the device program that streams to it",
                        description="Listen on HOST:PORT as a server driver, wait for a device program "
                                    "(hapticproxy device --server HOST:PORT ...) and check it against the rules. "
                                    "The engagement rule needs a scripted hand, e.g. --hand "
                                    "'{\"type\": \"constant\", \"wrench\": [0, 0.5, 0]}'.")
    pd.add_argument("--server", default=f"127.0.0.1:{dl.DEFAULT_PORT}", metavar="HOST:PORT",
                    help="where to listen (the device's --server)")
    pd.add_argument("--watchdog-s", type=float, default=dl.DEFAULT_WATCHDOG_S, help="the device's watchdog [s]")
    pd.add_argument("--slack-s", type=float, default=0.03, help="how much later than watchdog_s the cut may be seen")
    pd.add_argument("--timeout-s", type=float, default=30.0, help="how long to wait for the device's first STATE")
    pd.add_argument("--no-hand", action="store_true", help="the device has no scripted hand: leave the engagement rule out")
    ps = sub.add_parser("check-device-server", help="play a device and check the server driver it streams to",
                        description="Stream to the server driver at HOST:PORT as a device and check the server "
                                    "against the rules. The server must arm a device whose link is up before its "
                                    "first engagement (hapticproxy serve with driver = \"remote\" and no client).")
    ps.add_argument("--server", default=f"127.0.0.1:{dl.DEFAULT_PORT}", metavar="HOST:PORT",
                    help="the server driver's listen address")
    ps.add_argument("--kind", choices=tuple(dl.KINDS_BY_NAME), default="planar", help="the server's device kind")
    ps.add_argument("--link-timeout-s", type=float, default=dl.DEFAULT_LINK_TIMEOUT_S, help="the server's link timeout [s]")
    ps.add_argument("--slack-s", type=float, default=0.05, help="how much later than a deadline the server may react")
    ps.add_argument("--arm-timeout-s", type=float, default=5.0, help="how long to wait for the server to arm")
    for p in (pd, ps):
        p.add_argument("--rate", type=float, default=1000.0, metavar="HZ", help="the checker's rate (default 1000)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """``hapticproxy protocol check-device ...`` / ``check-device-server ...`` (argv starts with the mode)."""
    from .transport import UdpTransport  # imported late: keeps the module import light

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0) and 2
    try:
        host, port = _hostport(args.server)
        rate = _positive("--rate", args.rate, 1.0, 20000.0)
        if args.mode == "check-device":
            tr = UdpTransport(host, port, "server", max_packet_bytes=dl.MAX_DATAGRAM_BYTES)
            check = DeviceCheck(tr, period_s=1.0 / rate, watchdog_s=_positive("--watchdog-s", args.watchdog_s, 0.0, 10.0),
                                slack_s=_positive("--slack-s", args.slack_s, 0.0, 10.0),
                                hand=not args.no_hand, timeout_s=_positive("--timeout-s", args.timeout_s))
            print(f"check-device: listening on {host}:{tr.local_address[1]}; start the device with "
                  f"--server {host}:{tr.local_address[1]}", flush=True)
        else:
            tr = UdpTransport(host, port, "client", max_packet_bytes=dl.MAX_DATAGRAM_BYTES)
            check = ServerCheck(tr, kind=args.kind, period_s=1.0 / rate,
                                link_timeout_s=_positive("--link-timeout-s", args.link_timeout_s, 0.0, 60.0),
                                slack_s=_positive("--slack-s", args.slack_s, 0.0, 10.0),
                                arm_timeout_s=_positive("--arm-timeout-s", args.arm_timeout_s),
                                reopen=lambda: UdpTransport(host, port, "client", max_packet_bytes=dl.MAX_DATAGRAM_BYTES))
            print(f"check-device-server: streaming to {host}:{port} as a {args.kind} device", flush=True)
    except (OSError, ValueError) as exc:
        print(f"hapticproxy protocol {args.mode}: {getattr(exc, 'strerror', None) or exc}", file=sys.stderr)
        return 2
    try:
        report = check.run(rate, timeout_s=(args.timeout_s if args.mode == "check-device" else 0.0) + 120.0)
    except KeyboardInterrupt:
        report = check.report
        report.fail_open("interrupted")
    finally:
        tr.close()
    print("\n".join(report.lines()), flush=True)
    return 0 if report.passed else 1


if __name__ == "__main__":
    sys.exit(main())
