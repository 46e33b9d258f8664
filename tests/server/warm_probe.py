"""Run in a fresh interpreter by test_warm.py: warm a loop, then drive it through every state
(engage, contact, silence, fade, Bye, idle, a stall trip, a non-finite fault, re-arm, stop) and
print how many kernel signatures appeared after warm-up (must be 0) and the loop's own count."""
from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import numpy as np  # noqa: E402
from server_harness import WallEnv, WatchdogDevice, make_settings  # noqa: E402

from hapticproxy.server.clock import SimClock  # noqa: E402
from hapticproxy.server.devices.base import load_device  # noqa: E402
from hapticproxy.server.loop import HapticLoop, kernel_signatures, kernels_compiled  # noqa: E402
from hapticproxy.server.shm import ST  # noqa: E402


def main(kind: str) -> None:
    clock = SimClock(start_ns=1_000_000_000)
    tool = ""
    dev_kind = kind
    if kind == "linkage":
        tool, dev_kind = "linkage", "planar"
    elif kind == "planar-watchdog":
        dev_kind = "planar"
    settings = make_settings(device={"driver": "sim", "kind": dev_kind}, model={"tool": tool})
    if kind == "planar-watchdog":
        dev = WatchdogDevice(clock, hand=lambda t: (0.0, -0.5, 0.0), period_s=1e-3)
    else:
        dev = load_device("sim", dict(settings["device"]), period_s=1e-3, clock_ns=clock.now_ns)
    loop = HapticLoop.build(settings, clock=clock, device=dev)
    loop.warm_up()
    n0 = kernels_compiled()
    sig0 = kernel_signatures()
    loop.start()
    url = settings["transport"]["url"]
    if tool == "linkage":
        from linkage_env import LinkageWallEnv
        env = LinkageWallEnv(url, clock)
    else:
        env = WallEnv(url, clock, kind=dev_kind if dev_kind != "planar" else "planar", start_pose=(0.0, 0.011, 0.0))

    def run(s):
        for _ in range(int(s * 1000)):
            env.service()
            loop.step()

    run(1.5)                       # engage, ramp, contact
    env.alive = False
    run(0.5)                       # silent -> fading
    env.alive = True
    run(1.0)                       # resumed
    clock.stall(80_000_000)
    run(1.0)                       # a stall (a trip where the device has a watchdog), recovery
    loop.dev[0] = np.nan
    dev_read = loop.device.read
    loop.device.read = lambda s: (dev_read(s), s.__setitem__(0, np.nan))[0]
    run(0.05)                      # non-finite -> fault
    loop.device.read = dev_read
    loop.rearm()
    run(1.0)
    env.ep.close(now_ns=clock.now_ns())  # Bye
    env.alive = False
    run(0.5)                       # session ended -> fading -> idle
    loop.request_stop()
    run(0.3)
    from hapticproxy.server.lifecycle import LOOP_STATES
    visited = sorted({LOOP_STATES[t[3]] for t in loop.shared.transitions_since(0)})
    late = sorted(k for k, v in kernel_signatures().items() if v > sig0.get(k, 0))
    print(json.dumps({"after_warm_up": kernels_compiled() - n0, "late": late,
                      "late_compiles": loop.shared.status[ST["late_compiles"]], "state": loop.state_name,
                      "visited": visited, "stall_trips": loop.stall_trips}))


if __name__ == "__main__":
    main(sys.argv[1])
