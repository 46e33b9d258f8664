"""Clocks for the haptic loop: one interface, a real one and a simulated one.

The loop is scheduled on absolute deadlines (``deadline += period_ns``), so a late wake-up does
not shift every later step. ``wait_until(deadline_ns)`` returns the wake-up time; lateness is
``wake - deadline``.

``MonotonicClock`` waits in two phases (hybrid wait): a sleep until ``spin_ns`` before the
deadline, then a spin on the monotonic clock. The sleep phase always runs when there is time for
it, so the loop never spins a whole period (which under real-time scheduling would starve the
rest of the machine); ``spin_ns`` is calibrated from the measured sleep overshoot at start-up.

``SimClock`` is simulated time for deterministic tests: waiting jumps to the deadline, and a
test may add a compute time or a stall per step.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import struct
import time

_NS = 1_000_000_000


class Clock:
    """Interface: ``now_ns()`` and ``wait_until(deadline_ns) -> wake_ns``."""

    simulated = False

    def now_ns(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def wait_until(self, deadline_ns: int) -> int:  # pragma: no cover - interface
        raise NotImplementedError


class MonotonicClock(Clock):
    """``time.monotonic_ns`` with a hybrid sleep-then-spin wait."""

    def __init__(self, spin_ns: int = 100_000) -> None:
        if spin_ns < 0:
            raise ValueError(f"spin_ns: must be >= 0, got {spin_ns}")
        self.spin_ns = int(spin_ns)
        self.now_ns = time.monotonic_ns  # bound builtin: no Python frame per call

    def wait_until(self, deadline_ns: int) -> int:
        now = time.monotonic_ns()
        sleep_ns = deadline_ns - self.spin_ns - now
        if sleep_ns > 0:
            time.sleep(sleep_ns * 1e-9)
            now = time.monotonic_ns()
        while now < deadline_ns:
            now = time.monotonic_ns()
        return now

    def calibrate(self, samples: int = 200, sleep_ns: int = 200_000, quantile: float = 0.99,
                  floor_ns: int = 150_000, ceiling_ns: int = 400_000) -> int:
        """Measure how late ``time.sleep`` wakes and set ``spin_ns`` to its ``quantile`` plus a
        margin, clamped to [floor_ns, ceiling_ns]. Returns the chosen ``spin_ns``.

        The floor is 150 us: the p99 of 200 sleeps (37 us + 10 on this VM) says little of the tail
        that misses deadlines. With 47 us the clock thread's 1 kHz lateness p99 was 98 us and 0.089 %
        of deadlines were missed; with 150 us, 1 us and 0.015 % (4 kHz: p99.9 69 -> 33 us;
        ``bench loop --rate 1000|4000 --seconds 20 --loop clock-thread``, 2026-12-05). The compiled
        loops never spin more than ``tick.SPIN_MAX_SHARE`` of the period."""
        late = []
        for _ in range(samples):
            t0 = time.monotonic_ns()
            time.sleep(sleep_ns * 1e-9)
            late.append(time.monotonic_ns() - t0 - sleep_ns)
        late.sort()
        q = late[min(len(late) - 1, int(quantile * len(late)))]
        self.spin_ns = int(min(max(q + 10_000, floor_ns), ceiling_ns))
        return self.spin_ns


class SleepClock(Clock):
    """The naive baseline: ``time.sleep`` until the deadline, nothing else (for comparison)."""

    def __init__(self) -> None:
        self.now_ns = time.monotonic_ns

    def wait_until(self, deadline_ns: int) -> int:
        d = deadline_ns - time.monotonic_ns()
        if d > 0:
            time.sleep(d * 1e-9)
        return time.monotonic_ns()


class SimClock(Clock):
    """Simulated time: ``wait_until`` jumps to the deadline (or stays if already past).

    ``step_cost_ns`` is added by ``charge()`` (the loop calls it after each step's work) to model
    compute time; ``stall(ns)`` makes the next wake-up late by ``ns`` (a stopped process).
    """

    simulated = True

    def __init__(self, start_ns: int = 0, step_cost_ns: int = 0) -> None:
        self.t = int(start_ns)
        self.step_cost_ns = int(step_cost_ns)
        self._stall = 0

    def now_ns(self) -> int:
        return self.t

    def wait_until(self, deadline_ns: int) -> int:
        if self.t < deadline_ns:
            self.t = deadline_ns
        if self._stall:
            self.t += self._stall
            self._stall = 0
        return self.t

    def charge(self) -> None:
        self.t += self.step_cost_ns

    def advance(self, ns: int) -> None:
        self.t += int(ns)

    def stall(self, ns: int) -> None:
        self._stall += int(ns)


# ------------------------------------------------------------------------------ process tuning
def set_timer_slack_ns(ns: int = 1) -> bool:
    """Linux ``prctl(PR_SET_TIMERSLACK)``: the default 50 us slack makes every sleep that late."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.prctl(29, ctypes.c_ulong(max(1, int(ns))), 0, 0, 0) == 0  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        return False


def try_realtime(priority: int = 80) -> tuple[bool, str]:
    """Ask for SCHED_FIFO at ``priority``; return (granted, why not)."""
    if not hasattr(os, "sched_setscheduler"):
        return False, "no sched_setscheduler on this platform"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True, ""
    except PermissionError as exc:
        return False, f"SCHED_FIFO refused: {exc.strerror} (needs CAP_SYS_NICE or an rtprio limit)"
    except OSError as exc:
        return False, f"SCHED_FIFO refused: {exc.strerror}"


def lower_fifo_priority() -> int | None:
    """Under SCHED_FIFO, this thread one priority lower (a thread it started keeps the higher one,
    and the kernel runs that one first where the two meet on a CPU: at equal FIFO priorities the
    running one keeps it). Returns the priority to restore, or None (not real-time, not allowed)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_FIFO:
            return None
        prio = os.sched_getparam(0).sched_priority
        if prio <= os.sched_get_priority_min(os.SCHED_FIFO):
            return None
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio - 1))
        return prio
    except (AttributeError, OSError):
        return None


def set_fifo_priority(prio: int) -> None:
    """This thread back to SCHED_FIFO at ``prio`` (what :func:`lower_fifo_priority` returned)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
    except OSError:
        pass


#: Linux's PM QoS request for the CPUs' wake-up latency (what cyclictest holds while it measures)
CPU_DMA_LATENCY = "/dev/cpu_dma_latency"


def hold_cpu_latency(max_us: int, path: str = CPU_DMA_LATENCY) -> tuple[int | None, str]:
    """Ask the kernel to keep every idle CPU able to wake within ``max_us`` (Linux PM QoS).

    Contract: returns ``(fd, "")`` when the request is in force; it holds for as long as ``fd``
    stays open (close it to withdraw it; the process's exit does too). Returns ``(None, why)``
    when it cannot be made (no such device, not permitted), changing nothing.

    Why: a deadline's wake-up is an idle CPU leaving its idle state. At 0 the cpuidle governor
    keeps idle CPUs polling instead of halting; in a VM a halted vCPU is woken by the host, which
    is most of a sleep's lateness (this 2-core VM, ``clock_nanosleep`` at 1 kHz: p50 33-34 us,
    p99 140-161 us halting against 16-17 / 33-45 us polling). The price: idle CPUs spin while
    the server runs, as the tick already does before each deadline."""
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError as exc:
        return None, f"{path}: {exc.strerror}"
    try:
        os.write(fd, struct.pack("i", int(max_us)))
    except OSError as exc:
        os.close(fd)
        return None, f"{path}: {exc.strerror}"
    return fd, ""


def parse_cpu_latency(text: str) -> int | None:
    """A command line's ``[loop] cpu_latency_us``: "off" -> None, a whole number of us in
    [0, 1000] -> it; anything else: ``ValueError`` saying what is taken."""
    if text == "off":
        return None
    if not text.isdigit() or int(text) > 1000:
        raise ValueError("must be off or a whole number of us in [0, 1000]")
    return int(text)


class HeldCpuLatency:
    """:func:`hold_cpu_latency` for a ``with`` block (``us`` None: nothing asked), withdrawn at
    its exit. ``held``: the latency in force inside it (None: not asked, or refused, ``why``
    saying why)."""

    def __init__(self, us: int | None, path: str = CPU_DMA_LATENCY) -> None:
        self.us, self.path, self.fd, self.why, self.held = us, path, None, "", None

    def __enter__(self) -> "HeldCpuLatency":
        if self.us is not None:
            self.fd, self.why = hold_cpu_latency(self.us, self.path)
            self.held = None if self.fd is None else self.us
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def clock_cpus(setting, allowed) -> tuple[int | None, frozenset | None, str]:
    """Where a clock thread ticks and where the loop's Python thread runs (``[loop] clock_cpu``).

    Contract: ``setting`` is "auto", -1 or a CPU number; ``allowed`` the CPUs the process may use.
    Returns ``(clock, python, why)``: ``clock`` a CPU in ``allowed`` and ``python`` the rest of
    ``allowed`` (never empty, never holding ``clock``), or ``(None, None, why)`` when nothing is
    pinned (``why`` empty when that was asked for or there is one CPU only, else the reason).
    "auto" is the highest CPU allowed (on most machines CPU 0 takes the most interrupts).

    Why: at 1 kHz the clock thread sleeps most of each period and the scheduler runs the Python
    thread on its CPU meanwhile; a kernel without full preemption lets a running system call
    finish before the woken clock thread gets the CPU (this VM's 1 kHz lateness p99.9 208-430 us
    unpinned, 1-2 us pinned: ``bench loop --rate 1000 --seconds 30``, 2026-12-05)."""
    allowed = frozenset(int(c) for c in allowed)
    if setting == -1 or len(allowed) < 2:
        return None, None, ""
    cpu = max(allowed) if setting == "auto" else int(setting)
    if cpu not in allowed:
        return None, None, f"CPU {cpu} is not one this process may use ({', '.join(map(str, sorted(allowed)))})"
    return cpu, allowed - {cpu}, ""


def pin_to_cpu(cpu: int | None) -> bool:
    """Keep the calling thread on ``cpu`` (Linux: ``sched_setaffinity(0)`` is this thread; threads
    it starts afterwards inherit it, so called before any, it pins the process). False when it
    could not (None, no such call, not permitted)."""
    if cpu is None or not hasattr(os, "sched_setaffinity"):
        return False
    try:
        os.sched_setaffinity(0, {int(cpu)})
        return True
    except (OSError, ValueError):
        return False
