"""``hapticproxy status --watch``: a live terminal view of a running server (textual).

It polls the status address (a UDP JSON request, ``status.query``) every ``--interval`` and
shows the state by name with the last transition's reason, faults by name, the device and
proxy pose, the commanded force and torque against the caps (bars), contacts (count, deepest
penetration), rates and lateness. ``q`` quits, ``r`` re-arms, ``s`` asks for a clean stop.
When the server stops answering, every panel is dimmed and titled with the age of what it shows
(the values are the last ones the server sent, not the present), until it answers again.
Nothing here touches the loop: the supervisor answers from shared memory.
"""
from __future__ import annotations

import math
import os
import time
from typing import Callable

from rich.table import Table
from rich.text import Text
from textual.app import App, ComposeResult
from textual.containers import Horizontal, Vertical
from textual.css.query import NoMatches
from textual.widgets import Footer, Header, Static

STATE_STYLE = {"engaged": "bold green", "idle": "cyan", "fading": "yellow", "fault": "bold white on red",
               "stopping": "magenta", "stopped": "magenta", "starting": "blue"}


def _n(v, fmt: str = ".3f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def _bar(value, cap, width: int = 18) -> Text:
    """|value| against the cap, as a bar with the signed value."""
    if value is None or not cap:
        return Text("-")
    frac = min(1.0, abs(value) / cap)
    n = int(round(frac * width))
    style = "red" if frac >= 0.999 else "yellow" if frac > 0.8 else "green"
    t = Text("[")
    t.append("#" * n, style=style)
    t.append(" " * (width - n) + "] ")
    t.append(f"{value:+.3f}")
    return t


def _euler_deg(q) -> tuple[float, float, float]:
    """Roll, pitch, yaw (deg) of a quaternion w x y z."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


def _label_grid() -> Table:
    """The panels' two-column grid: bold labels, then their values."""
    t = Table.grid(padding=(0, 1))
    t.add_column(style="bold")
    t.add_column()
    return t


def state_panel(s: dict) -> Table:
    t = _label_grid()
    state = s.get("loop_state", "?")
    t.add_row("state", Text(f" {state} ", style=STATE_STYLE.get(state, "")))
    fault = s.get("fault_name") or "none"
    t.add_row("fault", Text(fault, style="bold red" if fault != "none" else ""))
    dfault = s.get("device_fault_name") or "ok"
    t.add_row("device fault", Text(str(dfault), style="bold red" if dfault not in ("ok", "none", "0") else ""))
    tr = s.get("last_transition") or {}
    t.add_row("last change", f"{tr.get('from', '-')} -> {tr.get('to', '-')}" if tr else "-")
    t.add_row("reason", Text(str(tr.get("text", "-")), overflow="fold"))
    t.add_row("gain", _n(s.get("gain")))
    e = s.get("energy_hand_j")
    t.add_row("hand port", "-" if e is None else f"{e * 1e3:+.2f} mJ given to the hand")
    tank = s.get("tank_j")
    if tank is not None:
        t.add_row("tank", f"{tank * 1e3:.2f} mJ, limited {s.get('passivity_limited', 0)} steps")
    t.add_row("session", f"{s.get('session_id', 0)} ({s.get('device_kind', '?')} device, {s.get('tool_kind', '?')} tool)")
    return t


def pose_panel(s: dict) -> Table:
    t = Table(box=None, pad_edge=False, show_edge=False)
    t.add_column("")
    t.add_column("x mm", justify="right")
    t.add_column("y mm", justify="right")
    t.add_column("z mm", justify="right")
    t.add_column("roll", justify="right")
    t.add_column("pitch", justify="right")
    t.add_column("yaw deg", justify="right")
    lat = s.get("latest") or {}
    for name, key in (("device", "device_pose"), ("proxy", "proxy_pose")):
        p = lat.get(key)
        if not p:
            t.add_row(name, "-", "-", "-", "-", "-", "-")
            continue
        p = [math.nan if v is None else v for v in p]
        e = _euler_deg(p[3:7])
        t.add_row(name, *(f"{v * 1e3:+.2f}" for v in p[:3]), *(f"{v:+.2f}" for v in e))
    return t


def force_panel(s: dict) -> Table:
    t = _label_grid()
    lat = s.get("latest") or {}
    cmd = lat.get("command") or [None] * 6
    fcap, tcap = s.get("force_cap_n"), s.get("torque_cap_n_m")
    for i, a in enumerate(("fx", "fy", "fz")):
        t.add_row(f"{a} N", _bar(cmd[i], fcap))
    for i, a in enumerate(("tx", "ty", "tz")):
        t.add_row(f"{a} N m", _bar(cmd[3 + i], tcap))
    t.add_row("caps", f"{_n(fcap, '.2f')} N, {_n(tcap, '.2f')} N m per axis")
    return t


def contact_panel(s: dict) -> Table:
    t = _label_grid()
    lu = s.get("last_update") or {}
    t.add_row("contacts", str(s.get("contacts", 0)))
    pen = lu.get("penetration_m")
    t.add_row("deepest", "-" if pen is None else f"{pen * 1e3:.3f} mm penetration")
    t.add_row("updates", f"{s.get('updates', 0)} at {_n(s.get('env_rate_hz'), '.1f')} Hz")
    sil = s.get("env_silence_ms")
    t.add_row("silence", "no update yet" if sil is None else f"{sil:.0f} ms")
    return t


def timing_panel(s: dict) -> Table:
    t = _label_grid()
    lat, comp = s.get("lateness_us") or {}, s.get("compute_us") or {}
    t.add_row("rate", f"{_n(s.get('achieved_rate_hz'), '.1f')} Hz of {_n(s.get('rate_hz'), '.0f')}; "
                      f"{s.get('steps', 0)} steps")
    t.add_row("lateness us", f"p50 {lat.get('p50')}  p99 {lat.get('p99')}  p99.9 {lat.get('p999')}  "
                             f"max {_n(s.get('lateness_max_us'), '.0f')}")
    t.add_row("compute us", f"p50 {comp.get('p50')}  p99 {comp.get('p99')}  max {_n(s.get('compute_max_us'), '.0f')}")
    t.add_row("missed", f"{s.get('missed_deadlines', 0)} deadlines, {s.get('overruns', 0)} overruns")
    t.add_row("faults", f"{s.get('faults_total', 0)} total, {s.get('stall_trips', 0)} stall trips")
    return t


class WatchApp(App):
    """The live view. ``fetch()`` returns a status dict (or raises ``TimeoutError``); ``send(cmd)``
    sends a request (re-arm, stop)."""

    TITLE = "hapticproxy"
    CSS = """
    Static { border: round $accent; padding: 0 1; }
    #top, #bottom { height: auto; }
    #top Static, #bottom Static { width: 1fr; }
    #conn { border: none; height: 1; }
    Static.stale { opacity: 45%; color: $text-muted; }
    """
    BINDINGS = [("q", "quit", "quit"), ("r", "rearm", "re-arm"), ("s", "stop_server", "stop server")]

    def __init__(self, fetch: Callable[[], dict], *, send: Callable[[str], dict] | None = None,
                 interval_s: float = 0.2, address: str = "") -> None:
        super().__init__()
        self.fetch = fetch
        self.send = send
        self.interval_s = interval_s
        self.address = address
        self.last: dict | None = None
        self.panels: dict = {}  # panel id -> the rich renderable it shows now
        self.polls = 0
        self.misses = 0
        #: the panels show an answer that is no longer the present (the server stopped answering)
        self.stale = False
        self._last_answer = 0.0

    def compose(self) -> ComposeResult:
        yield Header()
        yield Static("", id="conn")
        with Vertical():
            with Horizontal(id="top"):
                yield Static("", id="state")
                yield Static("", id="timing")
            yield Static("", id="pose")
            with Horizontal(id="bottom"):
                yield Static("", id="force")
                yield Static("", id="contacts")
        yield Footer()

    def on_mount(self) -> None:
        for wid, title in self.PANELS:
            self.query_one(f"#{wid}", Static).border_title = title
        self.sub_title = self.address
        self.refresh_status()
        self.set_interval(self.interval_s, self.refresh_status)

    def refresh_status(self) -> None:
        try:
            self._refresh()
        except NoMatches:
            pass  # the app is closing: its widgets are gone before the last timer tick

    def _refresh(self) -> None:
        self.polls += 1
        try:
            s = self.fetch()
        except (TimeoutError, OSError, ValueError) as exc:
            self.misses += 1
            self.query_one("#conn", Static).update(Text(f"no answer: {exc}", style="bold red"))
            self._set_stale(True)
            return
        if "error" in s:
            self.query_one("#conn", Static).update(Text(f"server: {s['error']}", style="bold red"))
            return
        self.last = s
        self._last_answer = time.monotonic()
        self._set_stale(False)
        self.query_one("#conn", Static).update(Text(f"{s.get('url', '')}  {s.get('live', '')}", style="dim"))
        for wid, make in (("state", state_panel), ("timing", timing_panel), ("pose", pose_panel),
                          ("force", force_panel), ("contacts", contact_panel)):
            self.panels[wid] = make(s)
            self.query_one(f"#{wid}", Static).update(self.panels[wid])

    PANELS = (("state", "state"), ("timing", "rates and timing"), ("pose", "device and proxy pose"),
              ("force", "command against the caps"), ("contacts", "contacts"))

    def _set_stale(self, stale: bool) -> None:
        """Dim every panel (and say how old it is) while the server does not answer."""
        if stale == self.stale and not stale:
            return
        self.stale = stale
        age = f" (stale: last answer {time.monotonic() - self._last_answer:.0f} s ago)" if stale and self._last_answer \
            else " (stale: no answer yet)" if stale else ""
        for wid, title in self.PANELS:
            w = self.query_one(f"#{wid}", Static)
            w.set_class(stale, "stale")
            w.border_title = title + age

    def panel_text(self, wid: str, width: int = 100) -> str:
        """What panel ``wid`` shows, as plain text (tests, logs)."""
        from rich.console import Console

        con = Console(width=width, record=True, file=open(os.devnull, "w"))
        con.print(self.panels.get(wid, ""))
        return con.export_text()

    def _send(self, cmd: str) -> None:
        if self.send is None:
            return
        try:
            r = self.send(cmd)
            self.notify(f"{cmd}: {r.get('error') or 'ok'}", severity="error" if "error" in r else "information")
        except (TimeoutError, OSError, ValueError) as exc:
            self.notify(f"{cmd}: {exc}", severity="error")

    def action_rearm(self) -> None:
        self._send("rearm")

    def action_stop_server(self) -> None:
        self._send("stop")


def run_watch(address: str, query, *, key: bytes | None = None, interval_s: float = 0.2, timeout_s: float = 1.0) -> int:
    """``query``: ``status.query`` (given, so this view does not import the command that opens it)."""
    app = WatchApp(lambda: query(address, {"cmd": "status"}, timeout_s, key=key),
                   send=lambda cmd: query(address, {"cmd": cmd}, timeout_s, key=key),
                   interval_s=max(0.05, interval_s), address=address)
    app.run()
    return 0
