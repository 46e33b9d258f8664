"""Command-line entry point: ``hapticproxy [GLOBAL OPTIONS] COMMAND [ARGS]``.

Every command is one row of :data:`COMMANDS`: the module whose ``main(argv)`` runs it, imported
only when the command is chosen (so ``hapticproxy status`` pays for no numba compilation and
each subsystem owns its own argument parsing). A command with sub-targets (``bench TARGET``)
names one module per target. Adding a command is adding a row.

Global options, before or after the command: ``--version``; ``-v/--verbose`` (repeatable) and
``--log-level LEVEL`` (:mod:`hapticproxy.protocol.logs`: every log line has a timestamp).

Exit status, for every command: 0 success; 1 a failure at run time (no server answering, the
session refused or never opened, a transport or status address already taken); 2 bad usage or a
configuration that cannot work (unknown option or key, bad value, an address that cannot be
bound here); 130 interrupted (Ctrl-C) before the command could stop by itself (``serve`` stops
cleanly on Ctrl-C at any time, start-up included, and exits 0). Every failure is one line on
stderr, never a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field

from ..protocol.logs import ENV_LEVEL, ENV_VERBOSE, LEVELS, parse_level

PROG = "hapticproxy"


@dataclass(frozen=True)
class Command:
    """One subcommand: ``module.main(argv)`` runs it; ``targets`` (``bench``) maps its first
    argument to the module that runs it instead."""

    module: str
    help: str
    targets: Mapping[str, str] = field(default_factory=dict)


BENCH_TARGETS = {
    "model": "hapticproxy.benchmarks.bench_model",
    "codec": "hapticproxy.benchmarks.bench_codec",
    "transport": "hapticproxy.benchmarks.bench_transport",
    "loop": "hapticproxy.benchmarks.bench_loop",
    "floor": "hapticproxy.benchmarks.bench_floor",
    "clients": "hapticproxy.benchmarks.bench_clients",
    "faults": "hapticproxy.benchmarks.bench_faults",
    "recorder": "hapticproxy.benchmarks.bench_recorder",
    "devices": "hapticproxy.benchmarks.bench_devices",
    "passivity": "hapticproxy.benchmarks.bench_passivity",
}

COMMANDS: dict[str, Command] = {
    "demo": Command("hapticproxy.experiments.demo", "run the main demo (headless) and write a plot"),
    "serve": Command("hapticproxy.server.daemon", "run the haptics server daemon (--config FILE)"),
    "status": Command("hapticproxy.server.status", "ask a running server for its live figures (--json)"),
    "client": Command("hapticproxy.clients.cli", "run an environment client (`hapticproxy client --list` names the engines)"),
    "device": Command("hapticproxy.server.devices.remote", "run a device program that streams to a server over UDP"),
    "plot": Command("hapticproxy.server.plot", "write PNG plots from a recording (.mcap or .hpt)"),
    "convert": Command("hapticproxy.server.convert", "convert a recording (.hpt, or a torn .mcap) to a complete MCAP file"),
    "protocol": Command("hapticproxy.protocol.conformance", "protocol conformance kit: check-client, check-server"),
    "experiment": Command("hapticproxy.experiments.cli", "reproduce the paper's figures; the speed/accuracy trade-off"),
    "bench": Command("", "benchmarks that print figures (" + ", ".join(BENCH_TARGETS) + ")", BENCH_TARGETS),
    "devices": Command("hapticproxy.cli.devices", "list the haptic devices connected (driver, model, serial) and the drivers that find none"),
    "plugins": Command("hapticproxy.cli.plugins", "list the engines, device drivers and transports (built-in and installed)"),
    "view": Command("hapticproxy.cli.view", "the 3-D view of a running server or a recording (rerun's viewer, served here)"),
    "warmup": Command("hapticproxy.cli.warmup", "compile every numba kernel now (set-up does it; later runs load them)"),
}


class _UsageError(Exception):
    pass


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("hapticproxy")
    except PackageNotFoundError:
        return "unknown (not installed)"


@dataclass
class GlobalOptions:
    verbose: int = 0
    log_level: str | None = None
    version: bool = False
    help: bool = False


def split_global(argv: list[str]) -> tuple[GlobalOptions, str | None, list[str]]:
    """(global options, command, the command's own arguments). ``-v``/``-vv``/``--verbose``,
    ``--log-level LEVEL`` and ``--version`` are taken wherever they stand (no command has options
    of those names), up to a ``--``; ``-h`` only before the command (after it, it is the
    command's own help)."""
    g = GlobalOptions()
    command = None
    rest: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a == "--":
            rest.extend(argv[i:] if command is not None else argv[i + 1:])
            break
        if a == "--verbose" or (len(a) > 1 and a[0] == "-" and a[1:] == "v" * (len(a) - 1)):
            g.verbose += 1 if a == "--verbose" else len(a) - 1
        elif a == "--log-level" or a.startswith("--log-level="):
            if "=" in a:
                value = a.partition("=")[2]
            elif i + 1 < len(argv):
                i += 1
                value = argv[i]
            else:
                raise _UsageError(f"--log-level needs a level ({', '.join(LEVELS)})")
            try:
                parse_level(value)
            except ValueError as exc:
                raise _UsageError(str(exc)) from None
            g.log_level = value
        elif a == "--version":
            g.version = True
        elif command is None and a in ("-h", "--help"):
            g.help = True
        elif command is None and a.startswith("-"):
            raise _UsageError(f"unknown option {a!r} (global options: --version, -v/--verbose, --log-level LEVEL)")
        elif command is None:
            command = a
        else:
            rest.append(a)
        i += 1
    return g, command, rest


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description="Networked haptics server (local model of interaction).",
                                     epilog="Global options may also follow the command. Exit status: 0 success, "
                                            "1 run-time failure, 2 usage or configuration error, 130 interrupted.")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log lines (repeatable: -vv also shows other libraries' debug lines)")
    parser.add_argument("--log-level", choices=LEVELS, help="log level of every hapticproxy logger")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, cmd in COMMANDS.items():
        sub.add_parser(name, help=cmd.help, add_help=False)
    return parser


def _run_module(module_name: str, argv: list[str]) -> int:
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            print(f"{PROG}: {module_name} is not available in this build", file=sys.stderr)
            return 2
        raise
    return int(module.main(argv) or 0)


def dispatch(command: str, argv: list[str]) -> int:
    if command not in COMMANDS:
        _parser().print_usage(sys.stderr)
        print(f"{PROG}: unknown command {command!r}", file=sys.stderr)
        return 2
    cmd = COMMANDS[command]
    if cmd.targets:
        if not argv or argv[0] not in cmd.targets:
            print(f"{PROG} {command}: choose one of: {', '.join(cmd.targets)}", file=sys.stderr)
            return 2
        return _run_module(cmd.targets[argv[0]], argv[1:])
    return _run_module(cmd.module, argv)


def _quiet_stdout() -> None:
    """The reader of our stdout left (``| head``): point stdout at /dev/null so the flush at exit
    raises nothing."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def _take_sigint() -> bool:
    """Give SIGINT back to Python's default (a ``KeyboardInterrupt``) for a command that stops on
    it; False when a Ctrl-C came while the command line was starting (``cli.EarlyInterrupt``).
    ``serve`` keeps the recording handler until its supervisor installs its own, which reads it."""
    import signal

    from . import EarlyInterrupt

    early = signal.getsignal(signal.SIGINT)
    if not isinstance(early, EarlyInterrupt):
        return True
    signal.signal(signal.SIGINT, signal.default_int_handler)
    return not early.pending


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        g, command, rest = split_global(argv)
    except _UsageError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    if g.version:
        print(f"{PROG} {version()}")
        return 0
    if command is None:
        if g.help:
            _parser().print_help()
            return 0
        _parser().print_usage(sys.stderr)
        print(f"{PROG}: a command is required (hapticproxy --help lists them)", file=sys.stderr)
        return 2
    if command != "serve" and not _take_sigint():
        print(f"{PROG} {command}: interrupted", file=sys.stderr)
        return 130
    saved = {k: os.environ.get(k) for k in (ENV_LEVEL, ENV_VERBOSE)}
    if g.log_level is not None:
        os.environ[ENV_LEVEL] = g.log_level  # children (the loop process) inherit it
    if g.verbose:
        os.environ[ENV_VERBOSE] = str(g.verbose)
    try:
        return dispatch(command, rest)
    except KeyboardInterrupt:
        print(f"{PROG} {command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        _quiet_stdout()
        return 0
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


if __name__ == "__main__":
    sys.exit(main())
