"""hapticproxy.clients: environment clients (physics engines) for the haptics server.

- :mod:`.engine`: the engine interface (:class:`~.engine.Engine`, :class:`~.engine.ContactBuffer`).
- :mod:`.runner`: :class:`~.runner.ClientRunner`, the engine-neutral loop (handshake, stepping,
  one ContactUpdate per step, newest ProxyState followed only while the server renders it,
  heartbeats, reconnection; one injected clock).
- :mod:`.registry`: engines by name, the built-ins merged with any installed package's
  ``hapticproxy.engines`` entry points; :mod:`.contract`: the contract suite every engine passes, shipped
  so a lab runs it against its own.
- Engines (thin adapters): :mod:`.stub_engine` (Vortex-style analytic reference),
  :mod:`.pymunk_engine` (the paper's planar testbed; scene ``linkage``: a 3-bar chain held by its
  last link), :mod:`.peg_engine` (the paper's 1-DOF peg), :mod:`.pybullet_engine`,
  :mod:`.pybullet_linkage` (a URDF chain as the tool, its link records built from what pybullet
  loaded), sharing :mod:`.pybullet_common`.
- Shared pieces: :mod:`.geometry` (quaternions ``w x y z``, poses, planar and 1-DOF coordinates),
  :mod:`.narrowphase` (the 3-D engines' exact box contacts and clustering, numba),
  :mod:`.contacts` (feature keys, clustering), :mod:`.scenes` (planar scene geometry, the paper's
  Fig. 12).
- Windows: :mod:`.views` (what they show), :mod:`.gui` (pygame, for pymunk), :mod:`.pybullet_gui`;
  :mod:`.cli` (``hapticproxy client``).
"""
