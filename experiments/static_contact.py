"""The paper's static-contact experiment (its Figs. 13-14) on the real system.

The real server (supervisor + loop process, the simulated planar device pushed by a constant
hand wrench F = (0, 0.5 N, 0) towards the bottom wall), an environment client (the pymunk
testbed of Fig. 12 by default) over the real protocol on loopback, telemetry recorded by the
server. ``run_static_contact`` returns the figures; ``plot_static_contact`` draws them.

World frame as in ``clients/scenes.py``: +y points towards the bottom wall, whose top face is at
y = 134 mm, so the unrotated 20 mm peg rests on it with its centre at y_COM = 124 mm (the paper's
figure). The device is mapped onto the tool at engagement (indexing), so device and proxy share
world coordinates.
"""
from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

PUSH_N = 0.5


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class StaticContactResult:
    rate_hz: float
    achieved_rate_hz: float
    env_rate_hz: float
    updates: int
    contacts_max: int
    contacts_final: int
    wall_y_com_m: float
    felt_y_com_m: float
    final_force_n: float
    settled: bool
    faults: int
    lateness_p99_us: float | None
    t_s: np.ndarray = field(repr=False)
    proxy_y_m: np.ndarray = field(repr=False)
    device_y_m: np.ndarray = field(repr=False)
    force_y_n: np.ndarray = field(repr=False)
    contacts: np.ndarray = field(repr=False)
    recording: str = ""


def run_static_contact(*, seconds: float = 5.0, rate_hz: float = 512.0, epsilon_m: float = 0.005,
                       policy: str = "deformation", controller: str = "four_channel", engine: str = "pymunk",
                       url: str | None = None, record: str | Path | None = None, contact_frame: str = "engine",
                       log=None) -> StaticContactResult:
    from ..clients.runner import ClientRunner
    from ..clients.scenes import WALL_CONTACT_Y_COM_M
    from ..server import config as cfgmod
    from ..server import telemetry
    from ..server.daemon import Supervisor
    from ..server.shm import TEL

    url = url or f"udp://127.0.0.1:{_free_port()}"
    settings = cfgmod.load({
        "loop": {"rate_hz": rate_hz},
        "transport": {"url": url},
        "status": {"address": f"127.0.0.1:{_free_port()}"},
        "model": {"policy": policy, "epsilon_m": epsilon_m, "stiffness_n_per_m": 4000.0, "damping_n_s_per_m": 30.0,
                  "restitution": 0.0, "contact_frame": contact_frame},
        "controller": {"type": controller},
        # the paper's device is horizontal: no gravity; a workspace large enough for the testbed
        "device": {"driver": "sim", "kind": "planar", "workspace_min_m": [-0.25, -0.25],
                   "workspace_max_m": [0.25, 0.25], "hand": {"type": "constant", "wrench": [0.0, PUSH_N, 0.0]}},
        "telemetry": {"ring_s": max(10.0, seconds + 5.0)},
    })
    rec = str(record) if record else ""
    sup = Supervisor(settings, record=rec)
    if engine == "pymunk":
        from ..clients.pymunk_engine import PymunkEngine

        eng = PymunkEngine()
    elif engine == "stub":
        from ..clients.stub_engine import StubEngine

        eng = StubEngine()
    else:
        raise ValueError(f"engine: expected pymunk or stub, got {engine!r}")
    stop = threading.Event()
    runner = ClientRunner(eng, url, scene="testbed", epsilon_m=epsilon_m, max_contacts=16, connect_timeout_s=30.0)
    err: list[BaseException] = []

    def client():
        try:
            runner.run(stop)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller
            err.append(exc)

    th = threading.Thread(target=client, name="demo-client", daemon=True)
    try:
        sup.start()
        if log:
            log(f"server up ({settings.rate_hz:g} Hz, {url}); client: {engine} testbed")
        th.start()
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds and not err:
            sup._serve_status(0.05)
            if sup.writer is not None:
                sup.writer.drain(sup.shared)
        snap = sup.shared.snapshot()
        span = (snap["t_last_ns"] - snap["t_start_ns"]) * 1e-9
        achieved = (snap["steps"] - 1) / span if span > 0 else 0.0
        cstats = runner.stats()
        head = int(sup.shared.head[0])
        n = min(head, sup.ring_rows)
        idx = np.arange(head - n, head) % sup.ring_rows
        rows = sup.shared.ring[idx].copy()
    finally:
        stop.set()
        if th.is_alive():
            th.join(10)
        sup.close()
        eng.close()
    if err:
        raise RuntimeError(f"environment client failed: {err[0]}")
    # only the engaged part (after the first update)
    eng_rows = rows[rows[:, TEL["updates"]] > 0]
    if len(eng_rows) < 10:
        raise RuntimeError("the client never engaged the server")
    t = eng_rows[:, TEL["t_s"]] - eng_rows[0, TEL["t_s"]]
    proxy_y = eng_rows[:, TEL["proxy_y"]]
    dev_y = eng_rows[:, TEL["dev_y"]]
    fy = eng_rows[:, TEL["cmd_fy"]]
    contacts = eng_rows[:, TEL["contacts"]]
    last = t >= t[-1] - 1.0
    felt = float(np.mean(proxy_y[last]))
    settled = bool(np.ptp(dev_y[last]) < 1e-3)
    return StaticContactResult(
        rate_hz=settings.rate_hz, achieved_rate_hz=achieved, env_rate_hz=float(snap["env_rate_hz"]),
        updates=int(snap["updates"]), contacts_max=int(contacts.max()), contacts_final=int(contacts[-1]),
        wall_y_com_m=WALL_CONTACT_Y_COM_M, felt_y_com_m=felt, final_force_n=float(np.mean(fy[t >= t[-1] - 0.5])),
        settled=settled, faults=int(snap["faults_total"]), lateness_p99_us=snap["lateness_us"]["p99"],
        t_s=t, proxy_y_m=proxy_y, device_y_m=dev_y, force_y_n=fy, contacts=contacts, recording=rec)


def plot_static_contact(res: StaticContactResult, path: str | Path, title: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    axes[0].plot(res.t_s, res.device_y_m * 1e3, label="device (world)")
    axes[0].plot(res.t_s, res.proxy_y_m * 1e3, "--", label="proxy")
    axes[0].axhline(res.wall_y_com_m * 1e3, color="k", lw=0.8, label=f"wall (y_COM = {res.wall_y_com_m * 1e3:.0f} mm)")
    axes[0].set_ylabel("y_COM [mm]")
    axes[0].legend(loc="best", fontsize=8)
    axes[1].plot(res.t_s, res.force_y_n, label="force to the device, y")
    axes[1].axhline(-PUSH_N, color="k", lw=0.8, ls=":", label="balances the 0.5 N push")
    axes[1].set_ylabel("F_y [N]")
    axes[1].legend(loc="best", fontsize=8)
    axes[2].plot(res.t_s, res.contacts)
    axes[2].set_ylabel("local contacts")
    axes[2].set_xlabel("time since the client engaged [s]")
    fig.suptitle(title or "static contact (paper Fig. 14)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
