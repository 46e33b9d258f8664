"""Factory fixtures: a test makes as many things as it needs, and every one is ended at its end."""
from __future__ import annotations

from collections.abc import Callable, Iterator


def _close(thing) -> None:
    thing.close()


def made_then_ended(make_one: Callable, end: Callable = _close) -> Iterator[Callable]:
    """A factory fixture's body: ``yield from made_then_ended(Thing)``. Yields a function that
    makes ``make_one(*args, **kw)`` and remembers it; after the test, ``end`` (default: its
    ``close()``) is called on each thing made, in the order they were made. ``end`` is clean-up:
    it should not assert."""
    made = []

    def make(*args, **kw):
        made.append(make_one(*args, **kw))
        return made[-1]

    yield make
    for thing in made:
        end(thing)
