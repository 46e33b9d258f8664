"""Read-only properties declared in one line: an element of an array the object owns, or an
attribute the object writes and publishes.

The thin classes around the kernels (controller, model, simulated device, hand) keep their state
in preallocated arrays and expose a few elements as Python scalars for status, logs and tests::

    @dataclass
    class Hand:
        hp: np.ndarray
        mass_kg = ArrayFloat("hp", HP_M, doc="Mass of a gripping hand, kg.")

``hand.mass_kg`` is ``float(hand.hp[HP_M])``. Likewise ``epoch = ReadOnly[int]("_epoch")`` is
``obj._epoch``, read-only (the class alone writes it). All are ``property`` objects: ``help()``
lists them under "Readonly properties" with their docstring, assignment raises
``AttributeError``, and reading one is one call, as a hand-written property's is (``ReadOnly``'s
getter is :func:`operator.attrgetter`, no Python frame). Python-side read-outs only: kernels and
per-step code index the arrays themselves.
"""
from __future__ import annotations

from operator import attrgetter
from typing import TYPE_CHECKING, Any, Callable, Generic, TypeVar, overload

import numpy as np

T = TypeVar("T")


class _Typed(property, Generic[T]):
    """A property whose value type checkers see as ``T``."""

    if TYPE_CHECKING:  # at run time property's own (C) __get__ runs
        @overload
        def __get__(self, obj: None, owner: type | None = None) -> _Typed[T]: ...
        @overload
        def __get__(self, obj: object, owner: type | None = None) -> T: ...
        def __get__(self, obj: object, owner: type | None = None) -> Any: ...


class ReadOnly(_Typed[T]):
    """``obj.<attr>``, read-only: ``ReadOnly[int]("_epoch", doc=...)``."""

    def __init__(self, attr: str, *, doc: str | None = None) -> None:
        super().__init__(attrgetter(attr))
        self.attr = attr
        # (3.11 drops an explicit doc= of a property subclass: set the instance's own)
        self.__doc__ = doc if doc is not None else f"self.{attr}, read-only."

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.attr!r})"


class ArrayItem(_Typed[T]):
    """``cast(getattr(obj, array)[index])``, read-only; ``ArrayFloat``, ``ArrayInt`` and
    ``ArrayBool`` fix the cast."""

    def __init__(self, array: str, index: int, cast: Callable[[Any], T], doc: str | None = None) -> None:
        index = int(index)

        def read(obj: Any) -> T:
            return cast(getattr(obj, array)[index])

        super().__init__(read)
        self.array = array
        self.index = index
        self.__doc__ = doc if doc is not None else f"{cast.__name__}(self.{array}[{index}])"

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.array!r}, {self.index})"


class ArrayFloat(ArrayItem[float]):
    """``float(obj.<array>[index])``."""

    def __init__(self, array: str, index: int, *, doc: str | None = None) -> None:
        super().__init__(array, index, float, doc)


class ArrayInt(ArrayItem[int]):
    """``int(obj.<array>[index])``: a code or a count (kept in a float or an int64 array)."""

    def __init__(self, array: str, index: int, *, doc: str | None = None) -> None:
        super().__init__(array, index, int, doc)


class ArrayBool(ArrayItem[bool]):
    """``bool(obj.<array>[index])``: a flag kept as 0/1."""

    def __init__(self, array: str, index: int, *, doc: str | None = None) -> None:
        super().__init__(array, index, bool, doc)


def frozen_copies(*arrays) -> tuple:
    """Read-only copies of ``arrays``: what the decoder hands out (read-only views of a packet),
    for warm-ups that must compile the kernels for exactly those types."""
    out = []
    for a in arrays:
        a = np.array(a)
        a.flags.writeable = False
        out.append(a)
    return tuple(out)
