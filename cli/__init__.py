"""hapticproxy.cli

The first thing the ``hapticproxy`` command runs: a Ctrl-C from here on is recorded, not raised,
until the chosen command takes SIGINT over (``cli.main``). A ``KeyboardInterrupt`` raised in
the middle of an import or a finaliser would print a traceback, or be swallowed ("Exception
ignored in ...") and let ``serve`` start anyway; ``serve`` instead stops during start-up (exit 0),
every other command exits 130. What Python does before this line runs (its own start-up, the
``.pth`` files of an editable install) is out of reach.
"""
import signal as _signal


class EarlyInterrupt:
    """SIGINT handler that only records the signal (``pending``); read by ``cli.main`` and, for
    ``serve``, by the supervisor when it installs its own handler (it finds it with
    ``signal.getsignal``: ``server`` imports nothing from ``cli``)."""

    pending = False

    def __call__(self, signum, frame) -> None:  # noqa: ARG002
        self.pending = True


EARLY = EarlyInterrupt()
if _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler:  # not when SIGINT is ignored (nohup, &)
    _signal.signal(_signal.SIGINT, EARLY)
