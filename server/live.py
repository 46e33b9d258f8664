"""The live view: a Foxglove WebSocket server fed by the supervisor (``serve --live HOST:PORT``).

The supervisor reads the newest telemetry row and the newest contact-ring row from shared
memory (never the loop: the view costs the haptic loop nothing) and publishes, at ``rate_hz``
(30 Hz) and only while a client is subscribed:

- ``/scene`` (``foxglove.SceneUpdate``, frame ``world``): the device handle (blue sphere and its
  axes), the proxy's hand point (orange ghost cube), every contact of the last model update (red
  sphere, its normal as an arrow, scaled with the penetration), the commanded force at the
  device and the environment wrench at the proxy (arrows, 20 mm per N), the state as a label.
  Foxglove's 3D panel shows it for every device kind (a 1-DOF device moves along its axis, a
  planar one in x-y, a spatial one everywhere).
- ``/live/state`` (JSON, ``hapticproxy.LiveState``): the same numbers (poses, command, caps,
  contacts, state, reason) for plots, the Raw Messages panel, or a page of one's own
  (``docs/live_view.html`` draws it in a browser with no other software).

Open it in Foxglove: "Open connection" -> Foxglove WebSocket -> ``ws://HOST:PORT``.
"""
from __future__ import annotations

import math
import time

import msgspec
import numpy as np

from .recording import Num, json_schema

FORCE_M_PER_N = 0.02  # arrow length per newton
NORMAL_M = 0.015      # contact normal arrow length


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


def _quat_x_to(d) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) turning +x onto the unit vector d."""
    x, y, z = d
    # half-way vector between +x and d
    w = 1.0 + x
    if w < 1e-9:
        return (0.0, 0.0, 1.0, 0.0)  # d = -x: half a turn about z
    qx, qy, qz, qw = 0.0, -z, y, w
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    return (qx / n, qy / n, qz / n, qw / n)


class LiveView:
    """A Foxglove WebSocket server on ``address`` (``HOST:PORT``; port 0 picks a free one)."""

    def __init__(self, address: str, settings, t0_epoch_ns: int = 0, rate_hz: float = 30.0) -> None:
        import foxglove
        from foxglove.channels import SceneUpdateChannel

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
        if not (self.scene.has_sinks() or self.state.base.has_sinks()):
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
        if last_contacts is not None:
            _hdr, _key, pos, nrm, sep = last_contacts
            contacts = [LiveContact(pos[j].tolist(), nrm[j].tolist(), _fin(sep[j])) for j in range(len(sep))]
            pen = max(0.0, -float(np.min(sep))) if len(sep) else None
        msg = LiveState(float(row["t_s"]), state, _fin(row["gain"]), fault,
                        (last_transition or {}).get("text", ""), self.device_kind, _list(row["dev"][:7]),
                        _list(row["proxy"][:7]), _list(row["cmd"]), _list(row["env"]), _fin(st["force_cap_n"]),
                        _fin(st["torque_cap_n_m"]), contacts, pen)
        log_ns = self.t0_epoch_ns + int(msg.t_s * 1e9)
        self.state.base.log(self._enc.encode(msg), log_ns)
        self.scene.log(self.scene_update(msg), log_time=log_ns)
        self.frames += 1
        return True

    def scene_update(self, s: LiveState):
        from foxglove.messages import (
            ArrowPrimitive, Color, CubePrimitive, Pose, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive,
            TextPrimitive, Vector3,
        )

        def pose(p, q=(0.0, 0.0, 0.0, 1.0)):
            return Pose(position=Vector3(x=p[0], y=p[1], z=p[2]), orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))

        def q_of(p7):  # our w x y z -> Foxglove x y z w
            return (p7[4], p7[5], p7[6], p7[3])

        def arrow(origin, vec, length_per_unit, color, diameter=0.003):
            n = math.sqrt(sum(v * v for v in vec))
            if not n > 1e-9:
                return []
            d = [v / n for v in vec]
            length = n * length_per_unit
            return [ArrowPrimitive(pose=pose(origin, _quat_x_to(d)), shaft_length=0.7 * length,
                                   shaft_diameter=diameter, head_length=0.3 * length, head_diameter=2 * diameter,
                                   color=color)]

        blue, orange = Color(r=0.2, g=0.45, b=1.0, a=1.0), Color(r=1.0, g=0.55, b=0.1, a=0.45)
        red, green, purple = Color(r=0.9, g=0.1, b=0.1, a=1.0), Color(r=0.1, g=0.8, b=0.2, a=1.0), \
            Color(r=0.6, g=0.2, b=0.8, a=1.0)
        dev, prx = _nan0(s.device_pose), _nan0(s.proxy_pose)
        ents = [
            SceneEntity(frame_id="world", id="device", spheres=[SpherePrimitive(
                pose=pose(dev[:3], q_of(dev)), size=Vector3(x=0.012, y=0.012, z=0.012), color=blue)],
                arrows=arrow(dev[:3], _nan0(s.command[:3]), FORCE_M_PER_N, green)),
            SceneEntity(frame_id="world", id="proxy", cubes=[CubePrimitive(
                pose=pose(prx[:3], q_of(prx)), size=Vector3(x=0.02, y=0.02, z=0.02), color=orange)],
                arrows=arrow(prx[:3], _nan0(s.environment_wrench[:3]), FORCE_M_PER_N, purple),
                texts=[TextPrimitive(pose=pose([prx[0], prx[1], prx[2] + 0.03]), billboard=True, font_size=14.0,
                                     scale_invariant=True, color=Color(r=1, g=1, b=1, a=1),
                                     text=f"{s.state} gain {(s.gain or 0):.2f}  {len(s.contacts)} contacts")]),
        ]
        spheres, arrows = [], []
        for c in s.contacts:
            p = _nan0(c.position)
            spheres.append(SpherePrimitive(pose=pose(p), size=Vector3(x=0.004, y=0.004, z=0.004), color=red))
            arrows += arrow(p, _nan0(c.normal), NORMAL_M, red, 0.0015)
        ents.append(SceneEntity(frame_id="world", id="contacts", spheres=spheres, arrows=arrows))
        return SceneUpdate(entities=ents)

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


def _nan0(a) -> list[float]:
    return [0.0 if v is None or not math.isfinite(v) else float(v) for v in a]
