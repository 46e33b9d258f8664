"""Log lines of every command: a timestamp, the program, the message; one level setting for all.

``hapticproxy [-v|-vv|--log-level LEVEL] COMMAND ...`` (the options may also follow the
command) sets the level of every ``hapticproxy.*`` logger, the supervisor's, its loop process's
(a child inherits it through the environment) and the client's: each ``-v`` shows one level
more than the command's default (``serve``, ``client``, ``device``: info; the others: warning),
``-q`` one less, ``--log-level`` exactly that level. Other libraries log warnings and above
(``-vv`` or ``--log-level debug``: everything). The same settings come from the environment as
``HAPTICPROXY_LOG_LEVEL`` (a level name) and ``HAPTICPROXY_VERBOSE`` (a count), e.g. in a
systemd unit's ``Environment=``.

A line reads ``2026-11-21T10:00:00.123 hapticproxy serve: serving ...`` (local time, ms); a
warning or an error says so after the program's name.
"""
from __future__ import annotations

import logging
import os
import sys
import time

__all__ = ["ENV_LEVEL", "ENV_VERBOSE", "LEVELS", "configure", "effective_level", "level_name", "parse_level"]

ENV_LEVEL = "HAPTICPROXY_LOG_LEVEL"
ENV_VERBOSE = "HAPTICPROXY_VERBOSE"
LEVELS = ("debug", "info", "warning", "error", "critical")
_ROOT = "hapticproxy"


def parse_level(text: str) -> int:
    """A level name (any case) or number; ``ValueError`` naming the choices otherwise."""
    t = str(text).strip().lower()
    if t in LEVELS:
        return getattr(logging, t.upper())
    if t.isdigit():
        return int(t)
    raise ValueError(f"--log-level: expected one of {', '.join(LEVELS)}, got {text!r}")


def level_name(level: int) -> str:
    return logging.getLevelName(level).lower()


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        t = time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(record.created))
        who = record.name.replace(".", " ") if record.name.startswith(_ROOT) else record.name
        what = "" if record.levelno == logging.INFO else f"{record.levelname.lower()}: "
        text = f"{t}.{int(record.msecs):03d} {who}: {what}{record.getMessage()}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is when a line is logged (a test's capture, a redirect)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # the base class assigns it; the property wins
        pass


def effective_level(default: int = logging.INFO, quiet: int = 0) -> tuple[int, int]:
    """(level of the ``hapticproxy`` loggers, level of the others) from the environment (set by
    ``hapticproxy -v/--log-level``), the command's ``default`` and its ``-q`` count."""
    explicit = os.environ.get(ENV_LEVEL, "").strip()
    try:
        verbose = int(os.environ.get(ENV_VERBOSE, "0") or 0)
    except ValueError:
        verbose = 0
    if explicit:
        try:
            level = parse_level(explicit)
        except ValueError:
            level = default
    else:
        level = min(logging.CRITICAL, max(logging.DEBUG, default + 10 * (quiet - verbose)))
    others = logging.DEBUG if (verbose >= 2 or (explicit and level <= logging.DEBUG)) else max(level, logging.WARNING)
    return level, others


def configure(default: int = logging.INFO, *, quiet: int = 0) -> int:
    """Set up the log lines of this process (idempotent: a second call only sets the levels);
    returns the level of the ``hapticproxy`` loggers."""
    level, others = effective_level(default, quiet)
    root = logging.getLogger()
    handler = next((h for h in root.handlers if isinstance(h.formatter, _Formatter)), None)
    if handler is None:
        handler = _StderrHandler()
        handler.setFormatter(_Formatter())
        root.addHandler(handler)
    root.setLevel(others)
    logging.getLogger(_ROOT).setLevel(level)
    return level


def doc_summary(doc: str | None) -> str:
    """A command's ``--help`` description from its module docstring: the first paragraph whole
    (not its first line, which may stop mid-sentence), reST double backticks dropped."""
    first = (doc or "").strip().split("\n\n", 1)[0]
    return " ".join(first.replace("``", "").split())
