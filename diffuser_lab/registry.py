"""What a user extends is a registry entry: one small class for every registry of the package
(scene sources, prediction sources, protocols, fusion methods), each entry named by a config key."""
from __future__ import annotations

from typing import Iterable, TypeVar

from diffuser_lab.config import check_name

T = TypeVar("T")


class Registry(dict):
    """Entries (objects with a ``name``) by name, in the order they were added.

    Args:
        key: the config key whose value names an entry (``scene.source``).
        kind: what an entry is, in words (``scene source``).
        entries: the built-in ones.
        sort_names: list the names sorted in the one-line error (else in the registry's order).
    """

    def __init__(self, key: str, kind: str, entries: Iterable, sort_names: bool = False):
        super().__init__((e.name, e) for e in entries)
        self.key, self.kind, self.sort_names = key, kind, sort_names

    def register(self, entry: T) -> T:
        """Add an entry (a run started after this may name it); a name is registered once."""
        if entry.name in self:
            raise ValueError(f"{self.kind} {entry.name!r} is already registered")
        self[entry.name] = entry
        return entry

    def copy(self) -> "Registry":
        return Registry(self.key, self.kind, self.values(), self.sort_names)

    def names(self) -> list[str]:
        """The names, as the one-line error lists them."""
        return sorted(self) if self.sort_names else list(self)

    def named(self, name: str):
        """The entry named ``name``; :class:`~diffuser_lab.config.ConfigError` naming the key and
        the registered names otherwise."""
        check_name(self.key, name, self.names())
        return self[name]
