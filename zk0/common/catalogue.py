"""A catalogue of named dataset specs: the hand-written ones, and owner N of many made from its name.

zk0 generates every offline dataset from a spec looked up by name (the registry's entry names,
``zk0 assets``, the simulator's conditions). A federation of 16 or 64 owners needs as many specs;
rather than write them out, each is a pure function of its name (``synth-owner-7``: owner 7's
conditions drawn from a seeded distribution), so the registry, the asset generator and a SuperNode
on another machine all arrive at the same spec from the name alone.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Mapping
from typing import TypeVar

Spec = TypeVar("Spec")
MAX_OWNERS = 1000  # owner indices run 0-999: more than any simulated federation on one machine


class Catalogue(Mapping[str, Spec]):
    """``fixed`` specs by name, and any name matching one of ``families``' patterns made by that
    pattern's ``make(match)`` (a group ``index``, where the pattern has one: 0-999, written without
    leading zeros; ``make`` raises KeyError for a name its pattern matches but it does not make).

    Iterating lists only the fixed names (what ``zk0 assets`` makes by default); looking up or
    testing ``in`` also knows the generated ones.
    """

    def __init__(self, fixed: dict[str, Spec], families: dict[str, Callable[[re.Match], Spec]], shown: str) -> None:
        self._fixed = fixed
        self._families = [(re.compile(pattern), make) for pattern, make in families.items()]
        self.shown = shown  # how an error message names the generated ones, e.g. ``synth-owner-<N>``

    def __getitem__(self, name: str) -> Spec:
        if name in self._fixed:
            return self._fixed[name]
        for pattern, make in self._families:
            match = pattern.fullmatch(name) if isinstance(name, str) else None
            if match is None:
                continue
            index = match.groupdict().get("index")
            if index is not None and (int(index) >= MAX_OWNERS or index != str(int(index))):
                raise KeyError(name)
            return make(match)
        raise KeyError(name)

    def __iter__(self) -> Iterator[str]:
        return iter(self._fixed)

    def __len__(self) -> int:
        return len(self._fixed)

    def described(self) -> list[str]:
        """Every name an error message can offer: the fixed ones, then the generated ones' form."""
        return [*sorted(self._fixed), self.shown]
