"""A registry of words of one kind (predicates, skills): named entries in registration order, and a version that
changes whenever the set does, so that caches built from the vocabulary (spec validators) know when to rebuild."""

from __future__ import annotations

from typing import Generic, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    """Words of one kind by name. Defining a word twice is an error: a module cannot silently change another's."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.version = 0
        self._entries: dict[str, T] = {}

    def add(self, name: str, entry: T) -> T:
        if name in self._entries:
            raise ValueError(f"{self.kind} {name!r} is already defined")
        self._entries[name] = entry
        self.version += 1
        return entry

    def remove(self, name: str) -> T:
        entry = self._entries.pop(name)
        self.version += 1
        return entry

    def get(self, name: str) -> T | None:
        return self._entries.get(name)

    def entries(self) -> dict[str, T]:
        """Name -> entry, in registration order (a copy)."""
        return dict(self._entries)
