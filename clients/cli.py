"""``hapticproxy client ENGINE --scene NAME --connect URL``: run an environment client.

Examples::

    hapticproxy client pymunk --scene testbed                       # udp://127.0.0.1:9870
    hapticproxy client stub --scene wall --connect 10.0.0.5:9870 --seed 7
    hapticproxy client pymunk --scene push --connect zenoh://10.0.0.5:7447/lab --gui
    hapticproxy client pybullet --list-scenes
    hapticproxy client --list                                       # the registered engines
    hapticproxy client pymunk --scene linkage                       # a linkage tool (server: model.tool = "linkage")
    hapticproxy client pybullet-linkage --scene chain               # the URDF chain (spatial device)

Engines are found by name (:mod:`.registry`: the built-ins merged with any installed package's
``hapticproxy.engines`` entry points) and imported only when chosen, so an engine whose library
is missing does not affect the others. Exit status: 0 after a normal
stop (``--duration`` over, Ctrl-C / SIGTERM, or the session ended with ``--no-reconnect``) after
a session was open, 1 when no session ever opened (the server refused it, TLS or credentials
kept us out, nothing answered within ``--connect-timeout``, or the run ended first), 2 for bad
arguments; every failure is one line on stderr, never a traceback. For a ``zenoh://`` server,
``--connect-timeout`` bounds the Zenoh connect too (unless the URL sets ``connect_timeout_s``).
Session messages are log lines with a timestamp on stderr (``--quiet``: none; ``hapticproxy -v``:
more); ``--json`` prints the final statistics as strict JSON on stdout.
"""
from __future__ import annotations

import argparse
import importlib.util
import inspect
import logging
import math
import signal
import sys
import threading

from ..protocol import logs
from ..protocol.jsonout import print_json
from ..protocol.registry import format_rows

from .registry import REGISTRY, load_engine_class

__all__ = ["load_engine_class", "main"]

PROG = "hapticproxy client"


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, no usage block
        raise _UsageError(message)


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Run an environment client (physics engine) against a haptics server.",
                epilog="Units are SI: --epsilon is in metres (0.005 = 5 mm).")
    p.add_argument("engine", nargs="?", help="engine name (see --list)")
    p.add_argument("--list", action="store_true", help="print the registered engines (built-in and installed) and exit")
    p.add_argument("--scene", default=None, help="scene name (see --list-scenes; default: the engine's first)")
    p.add_argument("--connect", "--server", dest="connect", default="udp://127.0.0.1:9870",
                   help="server transport URL (udp://HOST:PORT, zenoh://HOST:PORT/SESSION, mem://NAME) or HOST:PORT "
                        "(default udp://127.0.0.1:9870)")
    p.add_argument("--transport", choices=("udp", "zenoh"), default="udp",
                   help="transport for a --connect given as HOST:PORT (default udp)")
    p.add_argument("--epsilon", type=float, default=0.005, help="epsilon of active geometry to request [m] (default 0.005)")
    p.add_argument("--max-contacts", type=int, default=None,
                   help="contact capacity to request (default: the protocol's most, so the server's capacity "
                        "decides: 16 for the fast preset, 32 balanced, 64 accurate)")
    p.add_argument("--rate", type=float, default=None, help="fixed engine step rate [Hz] (engines with a fixed rate)")
    p.add_argument("--seed", type=int, default=None, help="random seed (stub: its variable step rate)")
    p.add_argument("--gui", action="store_true", help="live window (pymunk: pygame, pip install 'hapticproxy[gui]'; pybullet: its own)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: run until Ctrl-C)")
    p.add_argument("--connect-timeout", type=float, default=10.0,
                   help="give up if no first session opens within this many seconds (default 10); after a "
                        "session ended the client keeps reconnecting and says so every this many seconds")
    p.add_argument("--no-reconnect", action="store_true", help="stop when the session ends instead of reconnecting")
    p.add_argument("--free-run", action="store_true", help="step back-to-back instead of at the engine's real-time rate")
    p.add_argument("--hmac-key-file", default=None,
                   help="shared secret as hex in a mode-600 file (or set HAPTICPROXY_HMAC_KEY[_FILE])")
    p.add_argument("--list-scenes", action="store_true", help="print the engine's scenes and exit")
    p.add_argument("--json", action="store_true", help="print the final statistics as JSON on stdout")
    p.add_argument("--quiet", action="store_true", help="no session messages on stderr")
    return p


def _url(connect: str, transport: str) -> str:
    from ..protocol.transport import parse_transport_url

    url = connect if "://" in connect else f"{transport}://{connect}"
    parse_transport_url(url)  # ValueError naming the problem
    return url


def _engine_kwargs(cls, args) -> dict:
    params = inspect.signature(cls).parameters
    wanted = {"seed": args.seed, "rate_hz": args.rate, "gui": args.gui or None}
    flags = {"seed": "--seed", "rate_hz": "--rate", "gui": "--gui"}
    kwargs = {}
    for key, value in wanted.items():
        if value is None:
            continue
        if key not in params:
            raise ValueError(f"{flags[key]} is not an option of engine {args.engine!r}")
        kwargs[key] = value
    return kwargs


def _most_contacts() -> int:
    from ..protocol.codec import Limits

    return Limits().max_contacts


def _check_numbers(args) -> None:
    if not (math.isfinite(args.epsilon) and args.epsilon >= 0):
        raise ValueError(f"--epsilon: must be a finite number of metres >= 0, got {args.epsilon!r}")
    if args.epsilon >= 1.0:
        raise ValueError(f"--epsilon is in metres: {args.epsilon!r} m is not plausible (5 mm is 0.005)")
    if args.max_contacts is not None and args.max_contacts < 1:
        raise ValueError(f"--max-contacts: must be >= 1, got {args.max_contacts}")
    for flag, v in (("--rate", args.rate), ("--duration", args.duration), ("--connect-timeout", args.connect_timeout)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"{flag}: must be a finite number > 0, got {v!r}")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = _parser().parse_args(argv)
    except _UsageError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    if args.list:
        return _list(args.json)
    if args.engine is None:
        print(f"{PROG}: the following arguments are required: engine (see --list)", file=sys.stderr)
        return 2
    try:
        _check_numbers(args)
        cls = load_engine_class(args.engine)
        if args.list_scenes:
            for name in cls.scenes():
                print(name)
            return 0
        if args.scene is None:
            args.scene = cls.scenes()[0]
        if "/" in args.scene or args.scene.endswith((".json", ".toml", ".yaml", ".py")):
            raise ValueError(f"--scene takes a scene name, not a file ({args.scene!r}); choose one of: "
                             f"{', '.join(cls.scenes())}")
        if args.scene not in cls.scenes():
            raise ValueError(f"unknown scene {args.scene!r} for engine {args.engine}; choose one of: "
                             f"{', '.join(cls.scenes())}")
        kwargs = _engine_kwargs(cls, args)
        for package in getattr(cls, "gui_packages", ()) if args.gui else ():
            if importlib.util.find_spec(package) is None:
                raise ValueError(f"--gui needs {package}, which is not installed (pip install 'hapticproxy[gui]')")
        url = _url(args.connect, args.transport)
        from ..protocol.session import load_hmac_key

        key = load_hmac_key(args.hmac_key_file)
    except _UsageError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    return _run(cls, kwargs, url, key, args)


def _list(as_json: bool) -> int:
    """One line per registered engine: name, where it comes from, and whether it loads here."""
    rows = REGISTRY.rows(lambda name, cls: {"scenes": list(cls.scenes())})
    for r in rows:
        r.setdefault("scenes", [])
        del r["kind"]
    if as_json:
        print_json(rows, sort_keys=True)
        return 0
    for line in format_rows(rows, lambda r: f"scenes: {', '.join(r['scenes'])}"):
        print(line)
    if not rows:
        print("no engines registered (is hapticproxy installed? pip install -e .)")
    return 0


def _transport_options(url: str, connect_timeout_s: float) -> dict:
    """Zenoh's own connect wait is bounded by ``--connect-timeout`` (its default is 5 s), unless
    the URL names ``connect_timeout_s`` itself."""
    from ..protocol.transport import parse_transport_url

    parsed = parse_transport_url(url)
    if parsed.scheme == "zenoh" and "connect_timeout_s" not in parsed.options:
        return {"connect_timeout_s": connect_timeout_s}
    return {}


def _run(cls, kwargs: dict, url: str, key, args) -> int:
    from .runner import ClientError, ClientRunner

    logs.configure(logging.INFO, quiet=1 if args.quiet else 0)
    logger = logging.getLogger("hapticproxy.client")
    log = logger.info

    stop = threading.Event()
    engine = None
    runner = None
    code = 0
    stopped_by: list[str] = []  # what stopped the client from outside (the runner's last reason is not it)

    def stop_for(why: str):
        def handler(*_):
            stopped_by.append(why)
            stop.set()
        return handler

    previous = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    if previous is not None:
        signal.signal(signal.SIGTERM, stop_for("SIGTERM"))
    try:
        try:
            engine = cls(**kwargs)
            runner = ClientRunner(engine, url, scene=args.scene, epsilon_m=args.epsilon,
                                  max_contacts=args.max_contacts or _most_contacts(),
                                  hmac_key=key, realtime=not args.free_run, reconnect=not args.no_reconnect,
                                  connect_timeout_s=args.connect_timeout, log=log,
                                  transport_options=_transport_options(url, args.connect_timeout))
            window = getattr(engine, "window", None)  # the GUI (opened by load_scene) stops us when closed
            if window is not None:
                window.on_close = stop_for("the window was closed")
            runner.run(stop, duration_s=args.duration)
        except KeyboardInterrupt:
            stopped_by.append("Ctrl-C")
        except ClientError as exc:
            print(f"{PROG}: {exc}", file=sys.stderr)
            code = 1
        except (ValueError, OSError) as exc:
            print(f"{PROG}: {exc}", file=sys.stderr)
            code = 2 if runner is None else 1
        except Exception as exc:  # noqa: BLE001 - an engine bug: one line, not a traceback
            print(f"{PROG}: internal error in {args.engine}: {type(exc).__name__}: {exc}", file=sys.stderr)
            code = 1
    finally:
        if engine is not None:
            try:
                engine.close()
            except Exception:  # noqa: BLE001
                pass
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if runner is not None:
        st = runner.stats()
        why = stopped_by[0] if stopped_by else (st["end_reason"] or "interrupted")
        if code == 0 and not st["sessions"]:
            # a client that never had a session did not do its job, whatever stopped it
            print(f"{PROG}: no session with {url} before the client stopped "
                  f"({why})", file=sys.stderr)
            code = 1
        elif code == 0:
            log(f"stopped ({why}): {st['steps']} steps, {st['updates_sent']} updates, "
                f"{st['proxy_applied']} proxy states applied, {st['sessions']} session(s)")
        if args.json:
            print_json(st, sort_keys=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
