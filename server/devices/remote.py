"""Remote devices (entry point ``remote``) and the device-side program (``hapticproxy device``).

A device running in another process or on another machine (a real device with its own small
program, or ``hapticproxy device``, which runs a simulated one) streams its state to the server
every tick and receives wrenches back over the remote-device link: two fixed-layout datagrams,
STATE (device -> server) and COMMAND (server -> device), declared once in
:mod:`hapticproxy.protocol.devlink` and specified, with the reason for each rule, in SPEC.md's
appendix "The remote-device link" (its tables are generated from that declaration).

In short (SPEC has the whole rule set): each side keeps only the newest datagram by ``seq``
and drops and counts stale, duplicate, malformed and foreign ones; the device obeys a command only
if it is addressed to its own ``device_session`` and its key ``(server_session, epoch)`` is not
older than the newest it has seen; a *newer* key with the enable flag arms the output, and within
one key commands only update the wrench, so a cut (disable, the device's watchdog, a non-finite
command) lasts until the server's next ``enable()``; the server driver latches
``DEV_FAULT_LINK`` when no state arrives within ``link_timeout_s`` or the device restarted.

Sockets: both sides move datagrams through the protocol's
:class:`~hapticproxy.protocol.transport.Transport` interface (UDP by default; any transport may be
injected, e.g. ``mem://`` for lock-step tests, or an impaired one); the link's newest-wins, key
and watchdog logic is this module's, above the transport, as the session layer is for the
environment protocol (the transport contract leaves ordering to the layer above).

Server-side config (``[device]`` with ``driver = "remote"``; every key optional):

``kind`` = ``"planar"``
    The device's kind; a STATE of another kind latches ``DEV_FAULT_HARDWARE``.
``listen`` = ``"127.0.0.1:9872"``
    ``HOST:PORT`` where the server driver receives state (port 0: any free port).
``device_address`` = ``""``
    ``HOST:PORT`` of the device: state is accepted only from there and commands go there;
    empty: the first device heard (its source address).
``link_timeout_s`` = 0.1
    No state for longer than this -> ``DEV_FAULT_LINK``.
``connect_timeout_s`` = 0
    At start, wait up to this long for the first state (0: do not wait).
``max_force_n``, ``max_torque_n_m``, ``max_speed_m_per_s``, ``max_angular_speed_rad_per_s``,
``workspace_min_m``, ``workspace_max_m``, ``watchdog_s`` = as for the ``sim`` device of that kind
    The device's limits as reported to the loop (``watchdog_s``: the device program's own
    watchdog, 0.05 s for ``hapticproxy device``). The device program enforces its own limits;
    these should match them.

Device side: :class:`DeviceProgram` bridges any local :class:`DeviceDriver` (a simulated device
by default) to a server; ``hapticproxy device --kind planar --server HOST:PORT`` runs one (see
:func:`main`). ``hapticproxy protocol check-device`` checks a device program against the rules,
``check-device-server`` a server driver.
"""
from __future__ import annotations

import argparse
import math
import socket
import sys
import threading
import time
from typing import Annotated

import msgspec
import numpy as np
from msgspec import Meta

from ...protocol import devlink as dl
from ...protocol.devlink import COMMAND, F_ARMED, F_ENABLE, PREFIX_BYTES, STATE, STATE_V1, new_session
from ...protocol.transport import Transport, UdpTransport

from ..readonly import ReadOnly
from . import _check as ck
from . import sim as _sim
from .base import (
    DEV_FAULT_DISABLED, DEV_FAULT_HARDWARE, DEV_FAULT_LINK, DEV_FAULT_NAMES,
    DEV_FAULT_NONFINITE_COMMAND, DEV_FAULT_WATCHDOG, DEV_NSTATE, DEV_OK, DEVICE_KINDS, DS_BUTTONS, DS_HAND, DS_POSE,
    DS_TIME, DS_TWIST, DeviceDriver, DeviceInfo, DeviceLimits, info_from_limits,
)
from .layout import KIND_IDS

# The link carries the drivers' state row, kinds and fault codes: base.py takes them from devlink.
assert KIND_IDS == {name: int(k) for k, name in dl.KIND_NAMES.items()}

STATE_SIZE = STATE.size            # 240 (layout version 2: the row with the device's inputs)
STATE_V1_SIZE = STATE_V1.size      # 216 (version 1: the first 20 floats; an older device program)
COMMAND_SIZE = COMMAND.size        # 96

DEFAULT_LISTEN = f"127.0.0.1:{dl.DEFAULT_PORT}"
DEFAULT_LINK_TIMEOUT_S = dl.DEFAULT_LINK_TIMEOUT_S
DEFAULT_DEVICE_WATCHDOG_S = dl.DEFAULT_WATCHDOG_S
MAX_DRAIN = dl.MAX_DRAIN

__all__ = ["DeviceProgram", "RemoteDevice", "make_remote_device", "new_session", "parse_hostport", "main"]


def parse_hostport(key: str, value) -> tuple[str, int]:
    if not isinstance(value, str):
        raise ck.fail(key, f"expected HOST:PORT, got {value!r}")
    host, sep, port = value.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ck.fail(key, f"expected HOST:PORT, got {value!r}")
    return host, int(port)


def _udp(key: str, host: str, port: int, role: str) -> UdpTransport:
    """A UDP endpoint of the link's size limit: ``role="server"`` binds ``host:port``, a client
    connects there. ``ValueError`` naming ``key`` when the socket cannot be set up."""
    try:
        return UdpTransport(host, port, role, max_packet_bytes=dl.MAX_DATAGRAM_BYTES)
    except OSError as exc:
        what = "bind" if role == "server" else "reach"
        raise ck.fail(key, f"cannot {what} {host}:{port}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ck.fail(key, str(exc)) from None


def _peer_id(peer):
    """A UDP source address as ``(host, port)`` (IPv6 reports 4-tuples); other peers as they are."""
    if type(peer) is tuple and len(peer) > 2:
        return peer[:2]
    return peer


def _resolve(key: str, address: tuple[str, int]) -> tuple[str, int]:
    try:
        info = socket.getaddrinfo(address[0], address[1], type=socket.SOCK_DGRAM)
    except OSError as exc:
        raise ck.fail(key, f"cannot resolve {address[0]}: {exc.strerror or exc}") from None
    return info[0][4][:2]


class _LinkEnd:
    """What both ends of the device link share: the transport they own (``_tr``), the receive
    buffer (``_rx``), the counters (``_cnt``) and the drain of the socket (each end's
    ``_accept(n, peer, now)`` takes one datagram)."""

    _tr: Transport
    _rx: bytearray
    _cnt: dict[str, int]

    transport = ReadOnly[Transport]("_tr", doc="The transport this end owns (``close`` closes it).")

    @property
    def local_address(self) -> tuple[str, int]:
        """The UDP address of this end's socket (the server's: what ``hapticproxy device --server``
        is given)."""
        return tuple(self._tr.local_address[:2])

    def counters(self) -> dict[str, int]:
        """The link's counters with what the transport dropped before the link saw it."""
        out = dict(self._cnt)
        tc = self._tr.counters
        out["malformed"] += tc.dropped_oversize_recv + tc.dropped_empty
        out["recv_errors"] += tc.recv_errors
        return out

    def _drain(self, now: int) -> None:
        # (an ICMP port-unreachable while the other end does not listen is counted by the transport)
        recv_into = self._tr.recv_into
        rx = self._rx
        for _ in range(MAX_DRAIN):
            n, peer = recv_into(rx)
            if peer is None:
                return
            self._accept(n, peer, now)

    def _accept(self, n: int, peer, now: int) -> None:
        raise NotImplementedError


# =============================================================================== server side
REMOTE_COUNTERS = ("states", "stale", "duplicate", "malformed", "foreign", "old_session",
                   "kind_mismatch", "device_restarts", "link_losses", "device_faults",
                   "commands_sent", "send_errors", "unsent", "nonfinite_refused", "recv_errors")


class RemoteDevice(DeviceDriver, _LinkEnd):
    """The server side of a remote device: ``read`` drains the transport (non-blocking) and keeps
    the newest state; ``write`` sends one COMMAND datagram.

    ``transport``: a server-role :class:`~hapticproxy.protocol.transport.Transport` to use instead
    of binding UDP at ``listen`` (the driver closes it). ``device_address`` then pins a peer id of
    that transport. Starts disabled with ``DEV_FAULT_LINK`` latched (no state yet): call
    ``enable()`` once :attr:`link_up` is true.
    """

    name = "remote"

    def __init__(self, *, kind: str, limits: DeviceLimits, listen=("127.0.0.1", 0), device_address=None,
                 link_timeout_s: float = DEFAULT_LINK_TIMEOUT_S, clock_ns=None, session: int | None = None,
                 transport: Transport | None = None) -> None:
        if kind not in DEVICE_KINDS:
            raise ck.fail("device.kind", f"expected one of {', '.join(DEVICE_KINDS)}; got {kind!r}")
        self.kind = kind
        self._kind_id = KIND_IDS[kind]
        self._limits = limits
        self._clock = clock_ns if clock_ns is not None else time.monotonic_ns
        self._link_ns = int(round(link_timeout_s * 1e9))
        self._pinned = None
        if device_address is not None:
            self._pinned = device_address if transport is not None else _resolve("device.device_address", device_address)
        if transport is None:
            transport = _udp("device.listen", listen[0], listen[1], "server")
        elif transport.role != "server":
            raise ValueError(f"transport: the server driver needs a server-role transport, got a {transport.role}")
        self._tr = transport
        self.session = session if session is not None else new_session()
        self._rx = bytearray(max(dl.MAX_DATAGRAM_BYTES, transport.max_packet_bytes))
        self._rx_state = STATE.floats(self._rx)
        self._rx_state_v1 = STATE_V1.floats(self._rx)  # the same bytes, the first 20 floats
        self._tx = COMMAND.new_buffer()
        self._tx_wrench = COMMAND.floats(self._tx)
        self._finite = np.zeros(13, dtype=bool)
        self._state = np.zeros(DEV_NSTATE)
        self._state[3] = 1.0
        self._state[13:19] = np.nan
        self._state[DS_BUTTONS:] = np.nan
        self._cnt = dict.fromkeys(REMOTE_COUNTERS, 0)
        self._enabled = False
        self._fault = DEV_FAULT_LINK
        self._epoch = 0
        self._engagements = 0
        self._seq = 0
        self._dev_session = 0
        self._dev_addr = self._pinned
        self._state_seq = 0
        self._have_state = False
        self._last_rx_ns = 0
        self._dev_fault = DEV_OK
        self._dev_armed = False
        self._dev_key = (0, 0)

    # -- DeviceDriver ------------------------------------------------------------------------
    limits = ReadOnly[DeviceLimits]("_limits", doc="The device's limits (as configured).")

    @property
    def info(self) -> DeviceInfo:
        """The device program's figures are not sent over the link: the config's. Each side runs
        its own tick; the server driver is polled by the loop (the loop's clock paces commands)."""
        return info_from_limits(self.kind, self._limits, model=f"remote {self.kind}", vendor="",
                                driver=self.name, source="config (the link carries no device figures)")
    enabled = ReadOnly[bool]("_enabled", doc="Armed by ``enable`` (the device re-arms on the next command).")
    fault = ReadOnly[int]("_fault", doc="Latched ``DEV_FAULT_*`` code (``DEV_OK`` if none).")

    def on_engage(self) -> None:
        """A new session engaged: told to the device program in every later command."""
        self._engagements = (self._engagements + 1) & 0xFFFFFFFF

    def enable(self) -> None:
        """Arm: a new epoch (the device re-arms on its first command). A latched link or
        hardware fault stays while its cause does (no fresh state, or a kind mismatch)."""
        now = self._clock()
        self._drain(now)
        if self._fault == DEV_FAULT_LINK and not self._link_fresh(now):
            return
        if self._fault == DEV_FAULT_HARDWARE and self._cnt_kind_bad:
            return
        self._fault = DEV_OK
        self._epoch = (self._epoch + 1) & 0xFFFFFFFF
        self._enabled = True

    def disable(self) -> None:
        """Zero now: a COMMAND with the enable flag clear goes out at once."""
        self._enabled = False
        self._send(None)

    def read(self, state_out: np.ndarray) -> int:
        now = self._clock()
        self._drain(now)
        self._check_link(now)
        state_out[:DEV_NSTATE] = self._state
        return self._status()

    def write(self, wrench: np.ndarray) -> int:
        now = self._clock()
        self._check_link(now)
        w = wrench
        if not (type(w) is np.ndarray and w.shape == (6,)):
            w = np.asarray(wrench, dtype=np.float64)
            if w.shape != (6,):
                raise ValueError(f"wrench: expected 6 numbers (fx fy fz tx ty tz), got shape {w.shape}")
        if not (math.isfinite(w[0]) and math.isfinite(w[1]) and math.isfinite(w[2])
                and math.isfinite(w[3]) and math.isfinite(w[4]) and math.isfinite(w[5])):
            self._cnt["nonfinite_refused"] += 1
            if self._fault == DEV_OK:
                self._fault = DEV_FAULT_NONFINITE_COMMAND
        live = self._enabled and self._fault == DEV_OK
        self._send(w if live else None)
        return self._status()

    def close(self) -> None:
        try:
            self.disable()
        finally:
            self._tr.close()

    # -- extras (and ``_LinkEnd``'s) ----------------------------------------------------------
    device_address = ReadOnly[object]("_dev_addr", doc="The device program's peer id: the pinned one, else the "
                                      "current device session's (None before any state).")
    device_session = ReadOnly[int]("_dev_session", doc="Boot session of the device whose state is used (0: none yet).")
    epoch = ReadOnly[int]("_epoch", doc="Arming epoch: ``enable`` starts a new one (sent in every COMMAND).")

    @property
    def link_up(self) -> bool:
        """State arrived within the link timeout (from the current device session)."""
        return self._link_fresh(self._clock())

    @property
    def device_armed(self) -> bool:
        """The device reports its output armed under this driver's current key."""
        return self._dev_armed and self._dev_key == (self.session, self._epoch)

    def status_text(self) -> str:
        return DEV_FAULT_NAMES.get(self._status(), f"fault {self._status()}")

    def wait_for_link(self, timeout_s: float) -> bool:
        """Poll (sleeping 1 ms) until a state arrives or ``timeout_s`` passes (real time)."""
        end = time.monotonic() + timeout_s
        while True:
            self._drain(self._clock())
            if self._have_state:
                return True
            if time.monotonic() >= end:
                return False
            time.sleep(0.001)

    # -- internals -----------------------------------------------------------------------------
    _cnt_kind_bad = False

    def _status(self) -> int:
        if self._fault != DEV_OK:
            return self._fault
        return DEV_OK if self._enabled else DEV_FAULT_DISABLED

    def _link_fresh(self, now: int) -> bool:
        return self._have_state and now - self._last_rx_ns <= self._link_ns

    def _check_link(self, now: int) -> None:
        if self._have_state and now - self._last_rx_ns > self._link_ns and self._fault != DEV_FAULT_LINK:
            self._cnt["link_losses"] += 1
            self._fault = DEV_FAULT_LINK
            self._send(None)

    def _send(self, wrench) -> None:
        if self._dev_addr is None or self._dev_session == 0:
            self._cnt["unsent"] += 1
            return
        self._seq += 1
        COMMAND.body.pack_into(self._tx, PREFIX_BYTES, 0 if wrench is None else F_ENABLE, self._dev_session,
                               self.session, self._epoch, self._engagements, self._seq, self._state_seq)
        if wrench is None:
            self._tx_wrench[:] = 0.0
        else:
            self._tx_wrench[:] = wrench
        if self._tr.send(self._tx, self._dev_addr):
            self._cnt["commands_sent"] += 1
        else:
            self._cnt["send_errors"] += 1

    def _accept(self, n: int, peer, now: int) -> None:
        addr = _peer_id(peer)
        cnt = self._cnt
        # the layout by its size: version 2 (with the device's inputs), or 1 (an older device
        # program, or a device without inputs: they are NaN then)
        if n == STATE_SIZE:
            layout = STATE
        elif n == STATE_V1_SIZE:
            layout = STATE_V1
        else:
            cnt["malformed"] += 1
            return
        (magic, version, ptype, flags, dev_session, srv_session, epoch, _period_us, seq, _cmd_seq,
         kind, fault) = STATE.header.unpack_from(self._rx, 0)
        if not layout.prefix_ok(magic, version, ptype):
            cnt["malformed"] += 1
            return
        np.isfinite(self._rx_state[:13], out=self._finite)
        if not (self._finite.all() and math.isfinite(self._rx_state[DS_TIME])):
            cnt["malformed"] += 1
            return
        if self._pinned is not None and addr != self._pinned:
            cnt["foreign"] += 1
            return
        if dev_session != self._dev_session:
            if dev_session < self._dev_session and self._link_fresh(now):
                # an older boot of the device while the current one is alive: a delayed datagram
                cnt["old_session"] += 1
                return
            if self._dev_session != 0:
                # a newer boot epoch (or any other one once the current device fell silent): the
                # device restarted; its output starts disarmed, and ours stays off until enable()
                cnt["device_restarts"] += 1
                self._fault = DEV_FAULT_LINK if self._fault == DEV_OK else self._fault
            self._dev_session = dev_session
            self._dev_addr = addr if self._pinned is None else self._pinned
            self._state_seq = 0
        elif addr != self._dev_addr:
            cnt["foreign"] += 1
            return
        if seq <= self._state_seq:
            cnt["duplicate" if seq == self._state_seq else "stale"] += 1
            return
        self._state_seq = seq
        self._last_rx_ns = now
        self._have_state = True
        if kind != self._kind_id:
            cnt["kind_mismatch"] += 1
            self._cnt_kind_bad = True
            if self._fault != DEV_FAULT_HARDWARE:
                self._fault = DEV_FAULT_HARDWARE
            return
        self._cnt_kind_bad = False
        cnt["states"] += 1
        if layout is STATE:
            self._state[:] = self._rx_state
        else:
            self._state[:DS_BUTTONS] = self._rx_state_v1
            self._state[DS_BUTTONS:] = np.nan
        self._dev_armed = bool(flags & F_ARMED)
        self._dev_key = (srv_session, epoch)
        self._dev_fault = fault
        if fault != DEV_OK and self._enabled and srv_session == self.session and epoch == self._epoch \
                and self._fault == DEV_OK:
            cnt["device_faults"] += 1
            self._fault = fault if fault in DEV_FAULT_NAMES and fault != DEV_FAULT_DISABLED else DEV_FAULT_HARDWARE


# The link's own keys, added to each kind's limits (``_sim.Limits*``): one declaration, three tables.
_LINK_KEYS = (
    ("driver", str, "remote"),
    ("listen", str, DEFAULT_LISTEN),
    ("device_address", str, ""),
    ("link_timeout_s", Annotated[float, Meta(gt=0.0, le=60.0)], DEFAULT_LINK_TIMEOUT_S),
    ("connect_timeout_s", Annotated[float, Meta(ge=0.0, le=600.0)], 0.0),
)
Remote1dof, RemotePlanar, RemoteSpatial = (
    msgspec.defstruct(f"Remote{name}", _LINK_KEYS, bases=(limits,), module=__name__)
    for name, limits in (("1dof", _sim.Limits1dof), ("Planar", _sim.LimitsPlanar), ("Spatial", _sim.LimitsSpatial)))

#: kind -> the ``[device]`` table of the ``remote`` driver
REMOTE_CONFIGS: dict[str, type] = {"1dof": Remote1dof, "planar": RemotePlanar, "spatial": RemoteSpatial}
REMOTE_KEYS = tuple(sorted({k for c in REMOTE_CONFIGS.values() for k in c.__struct_fields__}))


def parse_remote_config(config: dict, *, period_s: float) -> dict:
    """Validate a ``[device]`` table for the ``remote`` driver (:data:`REMOTE_CONFIGS`); returns
    the effective values: ``values`` (every key, config form) and the parsed ``listen``,
    ``device_address``, ``link_timeout_s``, ``connect_timeout_s``, ``limits``."""
    ck.num("period_s", period_s, lo=0.0, lo_open=True, hi=0.1)
    c = _sim.convert_kind(REMOTE_CONFIGS, config, default_driver="remote")
    out = {"driver": c.driver, "kind": c.kind}
    out["listen"] = parse_hostport("device.listen", c.listen)
    out["device_address"] = parse_hostport("device.device_address", c.device_address) if c.device_address else None
    if c.link_timeout_s < period_s:
        raise ck.fail("device.link_timeout_s", f"{c.link_timeout_s:g} s is shorter than one period ({period_s:g} s)")
    out["link_timeout_s"] = c.link_timeout_s
    out["connect_timeout_s"] = c.connect_timeout_s
    lo, hi, dims = _sim.workspace(c)
    c.workspace_min_m, c.workspace_max_m = lo[:dims].tolist(), hi[:dims].tolist()
    out["limits"] = _sim.limits_of(c, lo, hi)
    out["values"] = ck.table(c)
    return out


def effective_config(config: dict, *, period_s: float) -> dict:
    """The ``[device]`` table with every key of its kind, defaults filled in (``--print-config``)."""
    return parse_remote_config(config, period_s=period_s)["values"]


def make_remote_device(config: dict, *, period_s: float, clock_ns=None) -> RemoteDevice:
    """Entry point ``remote``: bind ``listen`` and wait up to ``connect_timeout_s`` for a device."""
    v = parse_remote_config(config, period_s=period_s)
    dev = RemoteDevice(kind=v["kind"], limits=v["limits"], listen=v["listen"], device_address=v["device_address"],
                       link_timeout_s=v["link_timeout_s"], clock_ns=clock_ns)
    if v["connect_timeout_s"] > 0:
        dev.wait_for_link(v["connect_timeout_s"])
    return dev


#: the config loader asks the driver for its effective table (``server/config.py``)
make_remote_device.effective_config = effective_config


# =============================================================================== device side
PROGRAM_COUNTERS = ("ticks", "states_sent", "send_errors", "commands", "stale", "duplicate", "malformed",
                    "foreign", "foreign_session", "old_key", "ignored_latched", "arms", "disarms", "watchdog_trips",
                    "nonfinite_refused", "driver_faults", "overruns", "recv_errors")


class DeviceProgram(_LinkEnd):
    """The device side: runs a local :class:`DeviceDriver` (``driver``) and bridges it to the
    server at ``server`` (host, port). One :meth:`tick` per device period: drain commands, the
    watchdog, ``driver.write``, ``driver.read``, one STATE datagram. :meth:`run` paces ticks.

    ``transport``: a :class:`~hapticproxy.protocol.transport.Transport` to the server instead of
    UDP to ``server`` (a client-role one; the program closes it). Without ``bind`` the UDP
    socket is connected to the server (the kernel drops datagrams from anyone else); with
    ``bind`` it is bound there and datagrams from other sources are dropped as foreign.

    The driver is enabled when a command arms the output and disabled when it is disarmed or a
    fault latches; the program's own faults (watchdog, non-finite command) and the driver's are
    reported in the state stream.
    """

    def __init__(self, driver: DeviceDriver, server: tuple[str, int] | None = None, *,
                 watchdog_s: float = DEFAULT_DEVICE_WATCHDOG_S, bind: tuple[str, int] | None = None, clock_ns=None,
                 period_s: float = 1e-3, session: int | None = None, transport: Transport | None = None) -> None:
        self.driver = driver
        self.server = server
        self._clock = clock_ns if clock_ns is not None else time.monotonic_ns
        self._wd_ns = int(round(watchdog_s * 1e9))
        self._period_us = int(round(period_s * 1e6))
        self.session = session if session is not None else new_session()
        self._peer = None      # where commands come from and states go (None: the client's one peer)
        if transport is None:
            if server is None:
                raise ValueError("server: give the server's (host, port) or a transport")
            if bind is None:
                transport = _udp("--server", server[0], server[1], "client")
            else:
                self._peer = _resolve("--server", server)
                transport = _udp("--bind", bind[0], bind[1], "server")
        elif transport.role == "server":
            if server is None:
                raise ValueError("server: a server-role transport needs the server's peer id")
            self._peer = server
        self._tr = transport
        self._kind_id = KIND_IDS[driver.kind]
        self._rx = bytearray(max(dl.MAX_DATAGRAM_BYTES, transport.max_packet_bytes))
        self._rx_wrench = COMMAND.floats(self._rx)
        # STATE version 2 carries the device's inputs (buttons, gripper); a device without any
        # sends version 1, which a server of the older layout takes too
        info = driver.info
        self._layout = dl.state_datagram_for(info.buttons > 0 or info.gripper)
        self._tx = self._layout.new_buffer()
        self._tx_state = self._layout.floats(self._tx)
        self._state = np.zeros(DEV_NSTATE)
        self._cmd = np.zeros(6)
        self._zero = np.zeros(6)
        self._key = (0, 0)
        self._engaged = (0, 0)  # (server session, its engagement count) last seen
        self._cmd_seq = 0
        self._seq = 0
        self._armed = False
        self._fault = DEV_OK
        self._last_cmd_ns = 0
        self._cnt = dict.fromkeys(PROGRAM_COUNTERS, 0)
        self.driver.disable()

    # -- state ---------------------------------------------------------------------------------
    armed = ReadOnly[bool]("_armed", doc="The output is armed (by a COMMAND with the enable flag under ``key``).")
    fault = ReadOnly[int]("_fault", doc="Latched ``DEV_FAULT_*`` code of the program or its driver (``DEV_OK``: none).")
    key = ReadOnly[tuple]("_key", doc="(server session, epoch) of the newest COMMAND's key.")

    @property
    def command(self) -> np.ndarray:
        """The wrench being rendered (zero when disarmed)."""
        return (self._cmd if self._armed else self._zero).copy()

    def close(self) -> None:
        self._disarm()
        self._tr.close()
        self.driver.close()

    # -- one period ------------------------------------------------------------------------------
    def tick(self) -> int:
        """One device period; returns the driver's status."""
        now = self._clock()
        self._drain(now)
        if self._armed and self._wd_ns > 0 and now - self._last_cmd_ns > self._wd_ns:
            self._cnt["watchdog_trips"] += 1
            self._latch(DEV_FAULT_WATCHDOG)
        self.driver.write(self._cmd if self._armed else self._zero)
        status = self.driver.read(self._state)
        if status not in (DEV_OK, DEV_FAULT_DISABLED) and self._armed:
            self._cnt["driver_faults"] += 1
            self._latch(status)
        self._send()
        self._cnt["ticks"] += 1
        return status

    def run(self, rate_hz: float, duration_s: float | None = None, stop: threading.Event | None = None) -> dict:
        """Tick at ``rate_hz`` on absolute deadlines (real time) until ``duration_s`` or ``stop``."""
        period_ns = int(round(1e9 / rate_hz))
        start = time.monotonic_ns()
        end = None if duration_s is None else start + int(duration_s * 1e9)
        deadline = start
        while not (stop is not None and stop.is_set()):
            self.tick()
            deadline += period_ns
            now = time.monotonic_ns()
            if end is not None and now >= end:
                break
            if now > deadline + 5 * period_ns:
                # fell behind (the process was stopped): skip ahead rather than burst
                self._cnt["overruns"] += 1
                deadline = now
            elif deadline > now:
                time.sleep((deadline - now) * 1e-9)
        return self.counters()

    # -- internals -----------------------------------------------------------------------------
    def _latch(self, fault: int) -> None:
        if self._fault == DEV_OK:
            self._fault = fault
        self._disarm()

    def _disarm(self) -> None:
        if self._armed:
            self._cnt["disarms"] += 1
        self._armed = False
        self._cmd[:] = 0.0
        self.driver.disable()

    def _send(self) -> None:
        self._seq += 1
        drv_fault = self.driver.fault
        fault = self._fault or (drv_fault if drv_fault not in (DEV_OK, DEV_FAULT_DISABLED) else DEV_OK)
        STATE.body.pack_into(self._tx, PREFIX_BYTES, F_ARMED if self._armed else 0, self.session, self._key[0],
                             self._key[1], self._period_us, self._seq, self._cmd_seq, self._kind_id, fault)
        self._tx_state[:] = self._state[:self._layout.block.count]
        if self._tr.send(self._tx, self._peer):
            self._cnt["states_sent"] += 1
        else:
            self._cnt["send_errors"] += 1

    def _accept(self, n: int, peer, now: int) -> None:
        want = self._peer
        if want is not None and _peer_id(peer) != want:
            self._cnt["foreign"] += 1
            return
        cnt = self._cnt
        if n != COMMAND_SIZE:
            cnt["malformed"] += 1
            return
        magic, version, ptype, flags, dev_session, srv_session, epoch, engagements, seq, _sseq = \
            COMMAND.header.unpack_from(self._rx, 0)
        if not COMMAND.prefix_ok(magic, version, ptype):
            cnt["malformed"] += 1
            return
        if dev_session != self.session:
            cnt["foreign_session"] += 1
            return
        key = (srv_session, epoch)
        if key < self._key:
            cnt["old_key"] += 1
            return
        if srv_session != self._engaged[0] or engagements > self._engaged[1]:
            if engagements > (self._engaged[1] if srv_session == self._engaged[0] else 0):
                self.driver.on_engage()  # a new session engaged the server: the hand's script starts
            self._engaged = (srv_session, engagements)
        enable = bool(flags & F_ENABLE)
        w = self._rx_wrench
        finite = (math.isfinite(w[0]) and math.isfinite(w[1]) and math.isfinite(w[2])
                  and math.isfinite(w[3]) and math.isfinite(w[4]) and math.isfinite(w[5]))
        if key == self._key:
            if seq <= self._cmd_seq:
                cnt["duplicate" if seq == self._cmd_seq else "stale"] += 1
                return
            self._cmd_seq = seq
            cnt["commands"] += 1
            if not enable:
                self._disarm()
            elif not self._armed:
                cnt["ignored_latched"] += 1
            elif not finite:
                cnt["nonfinite_refused"] += 1
                self._latch(DEV_FAULT_NONFINITE_COMMAND)
            else:
                self._cmd[:] = w
                self._last_cmd_ns = now
            return
        # a newer key: a new server session or the server's next enable()
        self._key = key
        self._cmd_seq = seq
        cnt["commands"] += 1
        if not enable:
            self._disarm()
            return
        if not finite:
            cnt["nonfinite_refused"] += 1
            self._fault = DEV_OK
            self._latch(DEV_FAULT_NONFINITE_COMMAND)
            return
        self._fault = DEV_OK
        self.driver.enable()
        self._armed = True
        self._cnt["arms"] += 1
        self._cmd[:] = w
        self._last_cmd_ns = now


# ================================================================================== the CLI
class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage block
        raise _UsageError(message)


def _build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="hapticproxy device",
                description="Bridge a haptic device on this machine to a server's remote driver: run any "
                            "registered device driver (the simulated device by default), stream its state to "
                            "the server over UDP and render the wrenches it sends back.")
    p.add_argument("--driver", default=None, metavar="NAME",
                   help="the device driver (`hapticproxy plugins --kind device` lists them; default: the "
                        "config's device.driver unless it is remote, else sim)")
    p.add_argument("--kind", choices=DEVICE_KINDS, default=None,
                   help="device kind (default: the config's, else the driver's: planar for sim)")
    p.add_argument("--server", required=True, metavar="HOST:PORT", help="the server driver's listen address")
    p.add_argument("--rate", type=float, default=1000.0, metavar="HZ", help="device rate [Hz] (default 1000)")
    p.add_argument("--hand", default=None, metavar="SPEC",
                   help='the simulated hand (--driver sim only): a type name (none, constant, sinusoid, steps, impedance) or a '
                        'JSON table, e.g. \'{"type": "sinusoid", "amplitude": [0, 0.5, 0], "frequency_hz": 2.5}\'')
    p.add_argument("--config", default=None, metavar="FILE",
                   help="a TOML file whose [device] table configures the driver (its keys; a server's file "
                        "with driver = \"remote\" configures the simulated device, its link keys ignored)")
    p.add_argument("--watchdog-s", type=float, default=DEFAULT_DEVICE_WATCHDOG_S, metavar="S",
                   help="no command this long -> zero output, latched until the server re-enables (default 0.05)")
    p.add_argument("--bind", default=None, metavar="HOST:PORT", help="local address of the device socket")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after this many seconds")
    p.add_argument("--quiet", action="store_true", help="no start and summary lines")
    return p


def _device_from_args(args) -> tuple[DeviceProgram, str]:
    """The device program the command line asks for: the driver (``--driver``, else the config's
    ``device.driver`` unless it is ``remote``, else ``sim``) built by :func:`base.load_device` from
    the config's ``[device]`` table (less the remote link's keys) and the flags."""
    import json
    import tomllib

    from .base import load_device

    if not (math.isfinite(args.rate) and 10.0 <= args.rate <= 20000.0):
        raise ValueError(f"--rate: expected 10..20000 Hz, got {args.rate:g}")
    if not (math.isfinite(args.watchdog_s) and 0.0 <= args.watchdog_s <= 10.0):
        raise ValueError(f"--watchdog-s: expected 0..10 s, got {args.watchdog_s:g}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ValueError(f"--duration: expected a positive number of seconds, got {args.duration:g}")
    server = parse_hostport("--server", args.server)
    if server[1] == 0:
        raise ValueError("--server: port 0 is not a server address")
    bind = parse_hostport("--bind", args.bind) if args.bind else None
    cfg: dict = {}
    if args.config:
        try:
            with open(args.config, "rb") as f:
                doc = tomllib.load(f)
        except OSError as exc:
            raise ValueError(f"--config: cannot read {args.config}: {exc.strerror or exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"--config: {args.config} is not valid TOML: {exc}") from None
        if not isinstance(doc.get("device", {}), dict):
            raise ValueError(f"--config: [device] in {args.config} is not a table")
        cfg = dict(doc.get("device", {}))
        for k, _, _ in _LINK_KEYS:
            cfg.pop(k, None)  # the server side's keys, when the same file configures both
        named = doc.get("device", {}).get("driver", "")
        if not isinstance(named, str):
            raise ValueError(f"--config: device.driver in {args.config} is not a name")
    else:
        named = ""
    driver = args.driver or (named if named and named != "remote" else "sim")
    if driver == "remote":
        raise ValueError("--driver: remote is the server's end of this link; name the driver of the device "
                         "here (sim, or one `hapticproxy plugins --kind device` lists)")
    cfg["driver"] = driver
    if args.kind:
        cfg["kind"] = args.kind
    if args.hand is not None and driver != "sim":
        raise ValueError(f"--hand: only the simulated device has a simulated hand (--driver sim), not {driver}")
    if args.hand is not None:
        spec = args.hand.strip()
        if spec.startswith("{"):
            try:
                hand = json.loads(spec)
            except json.JSONDecodeError as exc:
                raise ValueError(f"--hand: not valid JSON ({exc.msg} at column {exc.colno})") from None
        else:
            hand = {"type": spec}
        cfg["hand"] = hand
    period_s = 1.0 / args.rate
    dev = load_device(driver, cfg, period_s=period_s)
    try:
        prog = DeviceProgram(dev, server, watchdog_s=args.watchdog_s, bind=bind, period_s=period_s)
    except BaseException:
        dev.close()
        raise
    return prog, driver


def main(argv: list[str] | None = None) -> int:
    """``hapticproxy device --server HOST:PORT [--driver NAME] [--kind KIND] [--rate HZ] [--hand SPEC] ...``"""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
        prog, driver = _device_from_args(args)
    except _UsageError as exc:
        print(f"hapticproxy device: error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"hapticproxy device: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"hapticproxy device: error: {exc.strerror or exc}", file=sys.stderr)
        return 2
    import logging

    from ...protocol import logs

    logs.configure(logging.INFO, quiet=1 if args.quiet else 0)
    log = logging.getLogger("hapticproxy.device")
    drv = prog.driver
    host, port = prog.server
    log.info("%s %s device -> %s:%s at %g Hz (session %s, watchdog %g s)", drv.kind, driver, host, port,
             args.rate, prog.session, args.watchdog_s)
    if driver != "sim":
        log.info("%s", drv.info.summary())
    stop = threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        import signal

        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        prog.run(args.rate, args.duration, stop)
    except KeyboardInterrupt:
        pass
    finally:
        c = prog.counters()
        prog.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    log.info("%s", ", ".join(f"{k} {v}" for k, v in c.items() if v))
    return 0


if __name__ == "__main__":
    sys.exit(main())

#: for `hapticproxy plugins` and `hapticproxy devices`
make_remote_device.about = {"clock": "loop", "models": ["a device program over the remote-device link"]}
