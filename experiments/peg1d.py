"""The paper's 1-DOF peg-in-hole (its Figs. 5, 6 and 9), headless, on the real local model.

A 1 kg peg fits a hole exactly: its COM at x = 0 touches both walls; x > 0 penetrates the right
wall, x < 0 the left one. A small 1-DOF environment plays the engine: every ``env_period_s`` it
samples the tool pose it was last sent (the proxy's), computes both wall contacts, and its packet
reaches the model ``delay_s`` later. The hand is a controlled sinusoidal force and is directly
coupled (the paper's Fig. 5b): the hand force drives the proxy, the environment force goes
straight to the hand, so the hand position is the proxy position.

The hand-force frequency of the paper is garbled ("5 sin(2 pi / 10)"); we use 1 Hz
(``FIG6_FORCE_HZ``), slow against the contact's natural frequency (sqrt(K/m) = 100 rad/s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..server.model import ContactParams, LocalModel, ToolSpec

FIG6_MASS_KG = 1.0
FIG6_STIFFNESS_N_PER_M = 10000.0
FIG6_DAMPING_N_S_PER_M = 15.0
FIG6_DELAY_S = 0.020
FIG6_FORCE_AMPLITUDE_N = 5.0
FIG6_FORCE_HZ = 1.0

#: Half-width of the peg and of the hole (m); only the contact geometry depends on it.
PEG_HALF_WIDTH_M = 0.01


@dataclass
class PegRun:
    policy: str
    epsilon_m: float
    t_s: np.ndarray
    x_hand_m: np.ndarray
    f_hand_n: np.ndarray
    f_env_n: np.ndarray
    contacts: np.ndarray
    updates: int
    collisions: int
    nonfinite: int

    def amplitude_m(self, t0_s: float, t1_s: float) -> float:
        sel = (self.t_s >= t0_s) & (self.t_s < t1_s)
        return float(np.max(np.abs(self.x_hand_m[sel]))) if np.any(sel) else float("nan")

    @property
    def growth(self) -> float:
        """Peak |x| of the last second over the peak of the first second."""
        end = float(self.t_s[-1])
        first = self.amplitude_m(0.0, 1.0)
        return self.amplitude_m(end - 1.0, end + 1.0) / max(first, 1e-12)

    @property
    def unstable(self) -> bool:
        """Unstable: the hand's excursion keeps growing (x3 from the first to the last second),
        leaves the hole by more than a peg width, or the model had to refuse a non-finite step."""
        peak = float(np.max(np.abs(self.x_hand_m)))
        return bool(self.growth > 3.0 or peak > 2 * PEG_HALF_WIDTH_M or self.nonfinite > 0)

    def summary(self) -> str:
        return (f"{self.policy:<11} eps={self.epsilon_m * 1e3:.1f} mm  peak|x|={np.max(np.abs(self.x_hand_m)) * 1e3:8.3f} mm  "
                f"growth={self.growth:8.2f}  max|F_env|={np.max(np.abs(self.f_env_n)):9.2f} N  "
                f"updates={self.updates} collisions={self.collisions}  {'UNSTABLE' if self.unstable else 'bounded'}")


def wall_contacts(x_tool_m: float, epsilon_m: float | None):
    """Both hole walls as an engine reports them for a tool at x: keys, c_p, n, d.
    ``epsilon_m`` None reports both walls always; otherwise walls with d <= epsilon only."""
    w = PEG_HALF_WIDTH_M
    keys = np.array([[0, 1, 0], [0, 2, 0]], dtype=np.int64)
    cp = np.array([[-w, 0.0, 0.0], [w, 0.0, 0.0]])
    nrm = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    dsep = np.array([x_tool_m, -x_tool_m])
    if epsilon_m is not None:
        keep = dsep <= epsilon_m
        keys, cp, nrm, dsep = keys[keep], cp[keep], nrm[keep], dsep[keep]
    return keys, cp, nrm, dsep


def simulate_peg1d(
    policy: str,
    *,
    duration_s: float = 5.0,
    haptic_hz: float = 1000.0,
    delay_s: float = FIG6_DELAY_S,
    env_period_s: float = FIG6_DELAY_S,
    epsilon_m: float | None = None,
    stiffness_n_per_m: float = FIG6_STIFFNESS_N_PER_M,
    damping_n_s_per_m: float = FIG6_DAMPING_N_S_PER_M,
    mass_kg: float = FIG6_MASS_KG,
    force_amplitude_n: float = FIG6_FORCE_AMPLITUDE_N,
    force_hz: float = FIG6_FORCE_HZ,
    restitution: float = 0.0,
    runaway_m: float | None = None,
) -> PegRun:
    """``runaway_m``: stop the run early once the hand is this far from the hole's centre (an
    unstable run would otherwise grow to astronomic, meaningless numbers); the arrays end there."""
    dt = 1.0 / haptic_hz
    model = LocalModel(ToolSpec.one_dof(mass_kg),
                       ContactParams(stiffness_n_per_m, damping_n_s_per_m, restitution),
                       period_s=dt, policy=policy, epsilon_m=epsilon_m or 0.0, capacity=8)
    n = int(round(duration_s / dt))
    t = np.arange(n) * dt
    x = np.empty(n)
    fh = np.empty(n)
    fe = np.empty(n)
    nc = np.empty(n, dtype=np.int64)
    hand = np.zeros(1)
    in_flight: list[tuple[float, tuple]] = []      # (arrival time, contact set)
    next_env = 0.0
    for i in range(n):
        now = t[i]
        if now + 1e-12 >= next_env:
            # the engine samples the pose it was last sent and computes its contacts
            in_flight.append((now + delay_s, wall_contacts(float(model.q[0]), epsilon_m)))
            next_env += env_period_s
        while in_flight and in_flight[0][0] <= now + 1e-12:
            _, cs = in_flight.pop(0)
            model.update(*cs)
        hand[0] = force_amplitude_n * math.sin(2 * math.pi * force_hz * now)
        f = model.step(hand)
        x[i] = model.q[0]
        fh[i] = hand[0]
        fe[i] = f[0]
        nc[i] = model.contact_count
        if runaway_m is not None and not abs(x[i]) <= runaway_m:
            n = i + 1
            t, x, fh, fe, nc = t[:n], x[:n], fh[:n], fe[:n], nc[:n]
            break
    c = model.counters()
    return PegRun(policy, epsilon_m or 0.0, t, x, fh, fe, nc, c["updates"], c["collisions"], c["nonfinite"])


def plot_runs(runs: list[PegRun], path: str, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(runs), 1, figsize=(8, 2.6 * len(runs)), sharex=True, squeeze=False)
    for ax, run in zip(axes[:, 0], runs):
        ax.plot(run.t_s, run.x_hand_m * 1e3, lw=0.8)
        ax.set_ylabel("hand x (mm)")
        ax.set_title(f"{run.policy}: {'unstable' if run.unstable else 'bounded'} "
                     f"(peak {np.max(np.abs(run.x_hand_m)) * 1e3:.2f} mm)", fontsize=9)
        ax.grid(alpha=0.3)
        lim = max(1.0, min(np.max(np.abs(run.x_hand_m)) * 1e3 * 1.1, 50.0))
        ax.set_ylim(-lim, lim)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
