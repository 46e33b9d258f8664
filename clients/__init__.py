"""hapticproxy.clients: environment clients (physics engines) for the haptics server.

- :mod:`.engine`: the engine interface (:class:`~.engine.Engine`, :class:`~.engine.ContactBuffer`).
- :mod:`.runner`: :class:`~.runner.ClientRunner`, the engine-neutral loop (handshake, stepping,
  one ContactUpdate per step, newest ProxyState, heartbeats, reconnection).
- Engines: :mod:`.stub_engine` (Vortex-style analytic reference), :mod:`.pymunk_engine` (the
  paper's planar testbed; scene ``linkage``: a 3-bar chain held by its last link),
  :mod:`.pybullet_engine`, :mod:`.pybullet_linkage` (a URDF chain as the tool, its link records
  built from what pybullet loaded); registry in :data:`.cli.ENGINES`.
- :mod:`.scenes` (planar scene geometry, the paper's Fig. 12), :mod:`.contacts` (feature keys,
  clustering), :mod:`.cli` (``hapticproxy client``), :mod:`.gui` (optional pygame window).
"""
