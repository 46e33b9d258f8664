"""What the engines' live windows show, engine-neutral and without any window library: the
session's state as a snapshot of a :class:`~.runner.ClientRunner`, how each server state looks,
and the force on the hand. The pygame window (:mod:`.gui`) and pybullet's (:mod:`.pybullet_gui`)
draw from these, so both show the same thing the same way.

- **Server state** (``ProxyState.server_state``): engaged green, fading orange, fault red, idle
  grey; no session yet (or lost) grey too, labelled so. A 1.0/1.1 server does not report it: shown
  as engaged, labelled "not reported".
- **Proxy**: the pose of the newest ProxyState (a linkage: its root and joints), drawn as a
  ghost of the tool; while the server holds the proxy (not engaged) the ghost takes the state's
  colour.
- **Force on the hand**: ``ProxyState.wrench`` is the hand's wrench on the proxy (what the
  environment may apply to its tool); the device renders its reaction, so the hand feels
  ``-wrench``: an arrow pointing out of a wall the hand pushes into.
- **Contacts**: the reported ones (after clustering), red when the real tool penetrates
  (``d <= 0``), orange when predicted (``0 < d <= epsilon``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..protocol.messages import ServerState

__all__ = ["ViewState", "view_state", "state_style", "contact_colour", "PENETRATING_RGB", "PREDICTED_RGB",
           "PROXY_RGB", "FORCE_RGB"]

PENETRATING_RGB = (220, 30, 30)
PREDICTED_RGB = (240, 150, 20)
#: the ghost's colour while the proxy is rendered
PROXY_RGB = (40, 80, 220)
#: the arrow of the force on the hand
FORCE_RGB = (150, 0, 170)

_STYLES = {
    ServerState.ENGAGED: ("ENGAGED", (30, 160, 60)),
    ServerState.UNKNOWN: ("ENGAGED (state not reported)", (30, 160, 60)),
    ServerState.FADING: ("FADING: proxy held, force fading out", (240, 150, 20)),
    ServerState.FAULT: ("FAULT: output off, proxy held", (220, 30, 30)),
    ServerState.IDLE: ("IDLE: not rendered", (140, 140, 140)),
}
_NO_SESSION = ("NO SESSION", (140, 140, 140))


def state_style(server_state: int | None) -> tuple[str, tuple[int, int, int]]:
    """``(label, rgb)`` for a ``ProxyState.server_state`` (``None``: no session)."""
    if server_state is None:
        return _NO_SESSION
    try:
        return _STYLES[ServerState(int(server_state))]
    except ValueError:
        return (f"state {int(server_state)}", (140, 140, 140))


def contact_colour(separation_m: float) -> tuple[int, int, int]:
    return PENETRATING_RGB if separation_m <= 0.0 else PREDICTED_RGB


@dataclass
class ViewState:
    """One frame's worth of a session, copied (safe to keep while the runner goes on)."""

    #: ``ProxyState.server_state`` of the newest ProxyState; ``None``: no session / none yet
    server_state: int | None = None
    #: the newest ProxyState's proxy pose (x y z qw qx qy qz) and joints; ``None`` before the first
    proxy_pose: np.ndarray | None = None
    proxy_joint_position: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: the force (3) and torque (3) the hand feels: minus ``ProxyState.wrench``
    hand_wrench: np.ndarray = field(default_factory=lambda: np.zeros(6))
    #: the engine's tool pose of the last step
    tool_pose: np.ndarray | None = None
    #: granted epsilon [m] (the requested one before the Welcome)
    epsilon_m: float = 0.0
    contact_position_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    contact_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    contact_separation_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: is the proxy being rendered (the runner drives the tool towards it)
    following: bool = False


def view_state(runner) -> ViewState:
    """A :class:`ViewState` of ``runner`` (a :class:`~.runner.ClientRunner`) as it is now."""
    vs = ViewState()
    established = runner.state == "established"
    proxy = runner.last_proxy
    if established and proxy is not None:
        vs.server_state = int(getattr(proxy, "server_state", 0) or 0)
        vs.proxy_pose = np.array(proxy.proxy_pose, dtype=float)
        vs.proxy_joint_position = np.array(proxy.joint_position, dtype=float)
        vs.hand_wrench = -np.asarray(proxy.wrench, dtype=float)
        vs.following = runner.following
    vs.tool_pose = np.array(runner.tool_pose, dtype=float)
    vs.epsilon_m = float(runner.granted_epsilon_m if runner.granted_epsilon_m is not None
                         else runner.requested_epsilon_m)
    buf = runner.contacts
    n = buf.n if established else 0
    vs.contact_position_m = buf.position_m[:n].copy()
    vs.contact_normal = buf.normal[:n].copy()
    vs.contact_separation_m = buf.separation_m[:n].copy()
    return vs
