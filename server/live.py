"""The live view: a Foxglove WebSocket server fed by the supervisor (``serve --live HOST:PORT``).

The supervisor reads the newest telemetry row and the newest contact-ring row from shared
memory (never the loop: the view costs the haptic loop nothing) and publishes, at ``rate_hz``
(30 Hz) and only while a client is subscribed:

- ``/scene`` (``foxglove.SceneUpdate``), ``/tf`` (``foxglove.FrameTransforms``), ``/device/pose``
  and ``/proxy/pose`` (``foxglove.PoseInFrame``): the 3-D scene of ``server/scene.py``, the same
  messages a recording carries: the device handle (blue sphere and its axes), the proxy drawn as
  the tool's own shape (the engaged client's Hello; until one, the tool kind's), every contact of
  the last model update (red sphere, its normal as an arrow, a patch of its surface), the
  commanded force at the device and the environment wrench at the proxy (arrows, 20 mm per N),
  the state as a label. Foxglove's 3D panel shows it for every device kind.
- ``/live/state`` (JSON, ``hapticproxy.LiveState``): the same numbers (poses, command, caps,
  contacts, state, reason) for plots, the Raw Messages panel, or a page of one's own
  (``docs/live_view.html`` draws it in a browser with no other software).

Open it in Foxglove: "Open connection" -> Foxglove WebSocket -> ``ws://HOST:PORT``, then the
layout ``docs/foxglove_layout.json`` (a 3D panel on ``/scene``, plots of the command). The SDK
speaks the protocol as ``foxglove.sdk.v1``; a client offering only the older
``foxglove.websocket.v1`` is refused in the handshake (an older Foxglove release).
"""
from __future__ import annotations

import math
import time

import msgspec
import numpy as np

from . import scene as scn
from .recording import Num, json_schema

FORCE_M_PER_N = scn.FORCE_M_PER_N
NORMAL_M = scn.NORMAL_M


class LiveContact(msgspec.Struct):
    position: list[float]   # m, world
    normal: list[float]
    separation_m: Num


class LiveState(msgspec.Struct):
    """What the live view shows, once per frame."""
    t_s: float
    state: str
    gain: Num
    fault: str
    reason: str
    device_kind: str
    device_pose: list[float]   # x y z qw qx qy qz, world
    proxy_pose: list[float]
    command: list[float]       # fx fy fz tx ty tz, device frame
    environment_wrench: list[float]
    force_cap_n: Num
    torque_cap_n_m: Num
    contacts: list[LiveContact]
    penetration_m: Num




class LiveView:
    """A Foxglove WebSocket server on ``address`` (``HOST:PORT``; port 0 picks a free one)."""

    def __init__(self, address: str, settings, t0_epoch_ns: int = 0, rate_hz: float = 30.0) -> None:
        import foxglove
        from foxglove.channels import FrameTransformsChannel, PoseInFrameChannel, SceneUpdateChannel

        host, _, port = address.rpartition(":")
        host = host.strip("[]") or "127.0.0.1"
        self.settings = settings
        self.t0_epoch_ns = int(t0_epoch_ns)
        self.period_s = 1.0 / rate_hz
        self.device_kind = settings["device"]["kind"]
        self._ctx = foxglove.Context()
        try:
            self.server = foxglove.start_server(name="hapticproxy", host=host, port=int(port or 0), context=self._ctx)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error type
            raise RuntimeError(f"live view {address}: cannot start the WebSocket server ({exc})") from None
        self.address = f"{host}:{self.server.port}"
        self.scene = SceneUpdateChannel("/scene", context=self._ctx)
        self.tf = FrameTransformsChannel("/tf", context=self._ctx)
        self.poses = (PoseInFrameChannel("/device/pose", context=self._ctx),
                      PoseInFrameChannel("/proxy/pose", context=self._ctx))
        #: what the proxy is drawn as: the tool kind's shape until the supervisor has a Hello's
        self.shape = scn.ToolShape.for_kind(settings.tool_kind if hasattr(settings, "tool_kind")
                                            else settings["device"]["kind"])
        self.state = foxglove.Channel("/live/state", schema=json_schema(LiveState) | {"title": "hapticproxy.LiveState"},
                                      context=self._ctx)
        self._enc = msgspec.json.Encoder()
        self._next = 0.0
        self.frames = 0

    def publish(self, shared, last_contacts, last_transition) -> bool:
        """One frame if it is time and someone listens; returns whether one was sent."""
        now = time.monotonic()
        if now < self._next:
            return False
        self._next = now + self.period_s
        if not (self.scene.has_sinks() or self.state.base.has_sinks() or self.tf.has_sinks()
                or any(p.has_sinks() for p in self.poses)):
            return False
        row = shared.latest_row()
        if row is None:
            return False
        snap_state = int(shared.stat[0]["loop_state"])
        from .lifecycle import LOOP_STATES, Fault

        state = LOOP_STATES[snap_state] if 0 <= snap_state < len(LOOP_STATES) else "?"
        try:
            fault = Fault(int(shared.stat[0]["fault"])).name.lower()
        except ValueError:
            fault = "?"
        st = shared.stat[0]
        contacts = []
        pen = None
        arrays = None
        if last_contacts is not None:
            _hdr, _key, pos, nrm, sep = last_contacts
            contacts = [LiveContact(pos[j].tolist(), nrm[j].tolist(), _fin(sep[j])) for j in range(len(sep))]
            pen = max(0.0, -float(np.min(sep))) if len(sep) else None
            arrays = (pos, nrm, sep)
        msg = LiveState(float(row["t_s"]), state, _fin(row["gain"]), fault,
                        (last_transition or {}).get("text", ""), self.device_kind, _list(row["dev"][:7]),
                        _list(row["proxy"][:7]), _list(row["cmd"]), _list(row["env"]), _fin(st["force_cap_n"]),
                        _fin(st["torque_cap_n_m"]), contacts, pen)
        log_ns = self.t0_epoch_ns + int(msg.t_s * 1e9)
        self.state.base.log(self._enc.encode(msg), log_ns)
        frame = scn.frame_of(msg.t_s, row["dev"][:7], row["proxy"][:7], row["cmd"], row["env"], arrays, state,
                             msg.gain or 0.0)
        self.tf.log(scn.foxglove_transforms(frame, log_ns), log_time=log_ns)
        for ch, pose in zip(self.poses, (frame.device_pose, frame.proxy_pose)):
            ch.log(scn.foxglove_pose(pose, log_ns), log_time=log_ns)
        self.scene.log(scn.foxglove_scene(frame, self.shape, log_ns), log_time=log_ns)
        self.frames += 1
        return True

    def close(self) -> None:
        try:
            self.server.stop()
        except Exception:  # noqa: BLE001
            pass


def _fin(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _list(a) -> list:
    return [v if math.isfinite(v) else None for v in (float(x) for x in a)]
