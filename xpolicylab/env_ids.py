"""The environment ids a served model sees, kept apart between the clients of one server.

Why: a model keeps its per-environment state (frame history, memory) under the ids its clients send, and every
client numbers its own environments (0, 1, ...). Two evaluators sharing a server (a launcher's workers, a sweep's
jobs run side by side, two people) would otherwise interleave two episodes under one id, and a stateful policy
would act on the other's frames without any error.

How: every connection gets a `ConnectionIds` of the server's one `EnvIdSpace`. A client's id reaches the model
unchanged while no other open connection holds it, so a server with one client at a time sees exactly the ids it
was sent; an id another connection holds is given a free one instead (the smallest free integer for an integer
id, `<id>#<n>` for a string), for as long as the connection stays open. Replies carry the client's own ids. When a
connection closes, its ids are released and returned, so that the server can tell the model to forget them
before another client is given them.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from itertools import count


class EnvIdSpace:
    """The ids held by the open connections of one server (the model's side)."""

    def __init__(self) -> None:
        self._held: set[Hashable] = set()

    def connection(self) -> ConnectionIds:
        """The ids of one new connection."""
        return ConnectionIds(self)

    def _take(self, wanted: Hashable) -> Hashable:
        if wanted in self._held:
            candidates = (count() if isinstance(wanted, int) else (f"{wanted}#{n}" for n in count(1)))
            wanted = next(c for c in candidates if c not in self._held)
        self._held.add(wanted)
        return wanted

    def _release(self, ids: Sequence[Hashable]) -> None:
        self._held.difference_update(ids)


class ConnectionIds:
    """One connection's ids: the client's id -> the id the model knows it by, fixed until the connection closes."""

    def __init__(self, space: EnvIdSpace) -> None:
        self._space = space
        self._model_ids: dict[Hashable, Hashable] = {}

    def to_model(self, env_ids: Sequence[Hashable]) -> list[Hashable]:
        """The model's ids for these client ids, each taken on first sight."""
        for env_id in env_ids:
            if env_id not in self._model_ids:
                self._model_ids[env_id] = self._space._take(env_id)
        return [self._model_ids[env_id] for env_id in env_ids]

    def release(self) -> list[Hashable]:
        """Give every id back (the connection closed); return the model's ids that were held."""
        held = list(self._model_ids.values())
        self._space._release(held)
        self._model_ids.clear()
        return held
