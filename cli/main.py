"""Command-line entry point: ``hapticproxy <subcommand>``.

Subcommands are dispatched lazily so that ``hapticproxy status`` does not pay for numba
compilation, and so that each subsystem owns its own argument parsing:

- ``demo``                      -> hapticproxy.experiments.demo.main(argv)
- ``bench TARGET ...``          -> hapticproxy.benchmarks.bench_<TARGET>.main(argv)
- ``protocol check-client|check-server ...`` -> hapticproxy.protocol.conformance.main(argv)
- ``serve``, ``status``, ``plot``, ``client``, ``device``: see ``COMMANDS``
"""
from __future__ import annotations

import argparse
import importlib
import sys

BENCH_TARGETS = {
    "model": "hapticproxy.benchmarks.bench_model",
    "codec": "hapticproxy.benchmarks.bench_codec",
    "transport": "hapticproxy.benchmarks.bench_transport",
    "loop": "hapticproxy.benchmarks.bench_loop",
    "clients": "hapticproxy.benchmarks.bench_clients",
    "faults": "hapticproxy.benchmarks.bench_faults",
    "recorder": "hapticproxy.benchmarks.bench_recorder",
}

COMMANDS = {
    "demo": ("hapticproxy.experiments.demo", "run the main demo (headless) and write a plot"),
    "protocol": ("hapticproxy.protocol.conformance", "protocol conformance kit: check-client, check-server"),
    "serve": ("hapticproxy.server.daemon", "run the haptics server daemon (--config FILE)"),
    "status": ("hapticproxy.server.status", "ask a running server for its live figures (--json)"),
    "plot": ("hapticproxy.server.plot", "write PNG plots from a recording (.mcap or .hpt)"),
    "convert": ("hapticproxy.server.convert", "convert a recording (.hpt, or a torn .mcap) to a complete MCAP file"),
    "client": ("hapticproxy.clients.cli", "run an environment client (`hapticproxy client --list` names the engines)"),
    "device": ("hapticproxy.server.devices.remote", "run a device program that streams to a server over UDP"),
    "experiment": ("hapticproxy.experiments.cli", "reproduce the paper's figures; the speed/accuracy trade-off"),
    "warmup": ("hapticproxy.cli.warmup", "compile every numba kernel now (set-up does it; later runs load them)"),
}


def _run_module(module_name: str, argv: list[str]) -> int:
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            print(f"hapticproxy: {module_name} is not available in this build", file=sys.stderr)
            return 2
        raise
    return int(module.main(argv) or 0)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="hapticproxy", description="Networked haptics server (local model of interaction).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    bench = sub.add_parser("bench", help="benchmarks that print figures (" + ", ".join(BENCH_TARGETS) + ")", add_help=False)
    del bench
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0 if argv else 2
    command, rest = argv[0], argv[1:]
    if command in COMMANDS:
        return _run_module(COMMANDS[command][0], rest)
    if command == "bench":
        if not rest or rest[0] not in BENCH_TARGETS:
            print(f"hapticproxy bench: choose one of: {', '.join(BENCH_TARGETS)}", file=sys.stderr)
            return 2
        return _run_module(BENCH_TARGETS[rest[0]], rest[1:])
    parser.print_usage(sys.stderr)
    print(f"hapticproxy: unknown command {command!r}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
