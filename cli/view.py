"""``hapticproxy view``: the 3-D view of a running server or of a recording, in rerun's viewer,
served from this machine (no internet: the viewer's web build ships inside the ``rerun-sdk``
wheel, ``pip install 'hapticproxy[view]'``).

    hapticproxy view                     # live: the server on the default status address
    hapticproxy view --config FILE.toml  # live: that server's status address (and HMAC key)
    hapticproxy view run.mcap            # a recording, on a timeline to scrub
    hapticproxy view run.mcap --save run.rrd    # the same as a rerun file (no viewer served)

It prints one line, ``view: open http://127.0.0.1:9090/?url=...`` (the browser page), and serves
until Ctrl-C. What it shows is ``server/scene.py``'s scene, the same the Foxglove topics of the
live view and of a recording carry: the device handle (blue) with its axes and the command
(green arrow, 20 mm per N), the proxy drawn as the tool's own shape (orange box: the engaged
client's Hello, else the kind's), every contact of the last model update (red points, their
normals, a grey patch of the surface each lies on), the environment's force at the proxy
(purple), the state as a label; z up, metres.

Live, it polls the server's status address 30 times a second (one small UDP request each: the
supervisor answers from shared memory, the haptic loop never sees it), so it runs anywhere that
reaches the status address, on its own core, and nothing in the server imports rerun.

Why rerun and not Foxglove's 3D panel: Foxglove's app is a web page served from foxglove.dev (its
desktop build is downloaded from there too), so a lab machine with no internet cannot open it;
rerun's viewer is a pip package. Foxglove still works where it can be reached: ``serve --live``
and every recording carry the same scene as ``foxglove.SceneUpdate`` (layout:
``docs/foxglove_layout.json``).
"""
from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..protocol.logs import doc_summary
from ..server import scene as scn

PROG = "hapticproxy view"
BLUE, GREEN, ORANGE, RED, PURPLE, GREY = ((51, 115, 255), (26, 204, 51), (255, 140, 26, 160), (230, 26, 26),
                                          (153, 51, 204), (150, 150, 150, 130))


def log_frame(rr, frame: scn.Frame, shape: scn.ToolShape) -> None:
    """One instant of the scene as rerun entities under ``world/`` (the timeline is the caller's)."""
    dev, prx = frame.device_pose, frame.proxy_pose
    rr.log("world/device", rr.Points3D([dev[:3]], radii=0.006, colors=[BLUE]))
    axes = [scn.rotate(scn.xyzw(dev), e) * 0.02 for e in np.eye(3)]
    rr.log("world/device/axes", rr.Arrows3D(origins=[dev[:3]] * 3, vectors=axes,
                                            colors=[(255, 50, 50), (50, 255, 50), (50, 100, 255)], radii=0.0008))
    _arrow(rr, "world/device/command", dev[:3], frame.command[:3], GREEN)
    boxes = scn.tool_boxes_world(frame, shape)
    rr.log("world/proxy/tool", rr.Boxes3D(centers=[b[0] for b in boxes], half_sizes=[np.asarray(b[2]) / 2 for b in boxes],
                                          quaternions=[rr.Quaternion(xyzw=b[1]) for b in boxes], colors=[ORANGE],
                                          fill_mode="solid", labels=[frame.label], show_labels=True))
    _arrow(rr, "world/proxy/environment_force", prx[:3], frame.environment_wrench[:3], PURPLE)
    n = len(frame.separation)
    rr.log("world/contacts/points", rr.Points3D(frame.position, radii=0.002, colors=[RED]))
    rr.log("world/contacts/normals", rr.Arrows3D(origins=frame.position, vectors=frame.normal * scn.NORMAL_M,
                                                 colors=[RED], radii=0.0008))
    if n:
        unit = frame.normal / np.maximum(np.linalg.norm(frame.normal, axis=1, keepdims=True), 1e-12)
        rr.log("world/contacts/surface", rr.Boxes3D(
            centers=frame.position, half_sizes=[(scn.PATCH_M / 2, scn.PATCH_M / 2, 0.0002)] * n,
            quaternions=[rr.Quaternion(xyzw=scn.quat_z_to(u)) for u in unit], colors=[GREY], fill_mode="solid"))
    else:
        rr.log("world/contacts/surface", rr.Clear(recursive=False))


def _arrow(rr, path: str, origin, force, color) -> None:
    f = np.asarray(force, dtype=float)
    if np.linalg.norm(f) > 1e-9:
        rr.log(path, rr.Arrows3D(origins=[origin], vectors=[f * scn.FORCE_M_PER_N], colors=[color], radii=0.0015))
    else:
        rr.log(path, rr.Clear(recursive=False))


def recording_frames(path: str | Path):
    """``(t_s, Frame)`` at ``scene.SCENE_HZ`` through a recording, the contacts applied by then,
    and the tool shape: the engaged client's, as recorded, else the one its tool kind implies."""
    from ..server import recording

    rec = recording.read(path)
    flat = rec.rows
    kind = rec.meta.get("tool_kind") or (rec.meta.get("config") or {}).get("device", {}).get("kind", "")
    recorded = rec.meta.get("tool_shape")  # the engaged client's (the last one recorded)
    if recorded and recorded.get("boxes"):
        shape = scn.ToolShape([(tuple(c), tuple(q), tuple(z)) for c, q, z in recorded["boxes"]],
                              recorded.get("source", "hello"))
    else:
        shape = scn.ToolShape.for_kind(kind)
    out = []
    contacts = rec.contacts
    ci = 0
    current = None
    next_t = -math.inf
    t_col = recording.TEL["t_s"]
    for row in flat:
        t = row[t_col]
        if not t >= next_t:
            continue
        next_t = t + 1.0 / scn.SCENE_HZ
        while ci < len(contacts) and contacts[ci]["t_s"] <= t:
            c = contacts[ci]
            current = (c["position_m"], c["normal"], c["separation_m"])
            ci += 1
        out.append((float(t), recording.scene_frame(row, current)))
    return shape, out


def frame_from_status(s: dict) -> scn.Frame | None:
    """The scene from a status reply (``latest`` and ``last_update``); None before the first row."""
    lt = s.get("latest")
    if not lt:
        return None
    lu = s.get("last_update") or {}
    contacts = None
    if lu.get("position_m") is not None:
        contacts = (np.asarray(lu["position_m"], dtype=float).reshape(-1, 3),
                    np.asarray(lu["normal"], dtype=float).reshape(-1, 3),
                    np.asarray(lu["separation_m"], dtype=float).reshape(-1))
    return scn.frame_of(lt["t_s"], lt["device_pose"], lt["proxy_pose"], lt["command"], lt["environment_wrench"],
                        contacts, str(s.get("loop_state", "")), s.get("gain") or 0.0,
                        s.get("energy_hand_j"))


def shape_from_status(s: dict) -> scn.ToolShape:
    boxes = s.get("tool_shape")
    if boxes:
        return scn.ToolShape([(tuple(b[0]), tuple(b[1]), tuple(b[2])) for b in boxes], s.get("tool_shape_source", "hello"))
    return scn.ToolShape.for_kind(s.get("tool_kind") or "")


def _start(rr, port: int, grpc_port: int, newest_first: bool = False) -> str:
    """Serve the data (gRPC) and the viewer (HTTP); the page's address. ``newest_first``: a
    viewer that connects late is sent the newest frames first (live: the present, not a replay of
    every frame since the view started, which a software-rendered page took minutes to catch up
    on: 195 s behind in one run), the older ones after."""
    uri = rr.serve_grpc(grpc_port=grpc_port, newest_first=newest_first)
    rr.serve_web_viewer(web_port=port, open_browser=False, connect_to=uri)
    return f"http://127.0.0.1:{port}/?url={uri}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog=PROG, description=doc_summary(__doc__))
    p.add_argument("recording", nargs="?", help="an MCAP recording to replay (default: the live server)")
    p.add_argument("--address", help="live: the server's status address HOST:PORT (default: the config's, or "
                                     "127.0.0.1:9871)")
    p.add_argument("--config", help="live: the server's config file (its status address and HMAC key)")
    p.add_argument("--key-file", help="live: the HMAC key file of a server that authenticates requests")
    p.add_argument("--port", type=int, default=9090, help="the web viewer's HTTP port (default 9090)")
    p.add_argument("--grpc-port", type=int, default=9876, help="the port the viewer reads the data from (default 9876)")
    p.add_argument("--save", metavar="FILE.rrd", help="write a rerun file instead of serving a viewer")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    args = p.parse_args(argv)
    try:
        import rerun as rr
    except ImportError:
        print(f"{PROG}: needs rerun-sdk, which is not installed (pip install 'hapticproxy[view]')", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if args.recording:
        try:
            shape, frames = recording_frames(args.recording)
        except (OSError, ValueError) as exc:
            print(f"{PROG}: {exc}", file=sys.stderr)
            return 2
        rr.init("hapticproxy", recording_id=Path(args.recording).stem, spawn=False)
        if args.save:
            rr.save(args.save)
        else:
            url = _start(rr, args.port, args.grpc_port)
        rr.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for t, frame in frames:
            rr.set_time("t", duration=t)
            log_frame(rr, frame, shape)
        if args.save:
            rr.disconnect()
            print(f"{PROG}: {len(frames)} frames of {args.recording} written to {args.save}")
            return 0
        print(f"{PROG}: {len(frames)} frames of {args.recording}; open {url}  (Ctrl-C stops)", flush=True)
        stop.wait(args.duration)
        return 0
    return _live(rr, args, stop)


def _live(rr, args, stop: threading.Event) -> int:
    from ..server.status import DEFAULT_ADDRESS, load_key, query

    try:
        key, cfg_address = load_key(args.config, args.key_file)
    except (OSError, ValueError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    address = args.address or cfg_address or DEFAULT_ADDRESS
    rr.init("hapticproxy", recording_id="live", spawn=False)
    if args.save:
        rr.save(args.save)
        url = args.save
    else:
        url = _start(rr, args.port, args.grpc_port, newest_first=True)
    rr.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    print(f"{PROG}: live from {address}; open {url}  (Ctrl-C stops)", flush=True)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    period = 1.0 / scn.SCENE_HZ
    frames = 0
    said = ""
    while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
        t_next = time.monotonic() + period
        try:
            s = query(address, {"cmd": "status"}, 0.5, key=key)
            why = s.get("error", "")
        except (TimeoutError, OSError, ValueError) as exc:
            s, why = {}, str(exc)
        if why != said:  # say when the server goes away and when it is back, once each
            print(f"{PROG}: {why or 'server answering again'}", file=sys.stderr, flush=True)
            said = why
        frame = frame_from_status(s) if not why else None
        if frame is not None:
            rr.set_time("t", duration=frame.t_s)
            log_frame(rr, frame, shape_from_status(s))
            frames += 1
        stop.wait(max(0.0, t_next - time.monotonic()))
    if args.save:
        rr.disconnect()
    return 0
