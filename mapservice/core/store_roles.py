"""The store handed out by role: each component gets the role ports it uses
(mapservice/core/ports.py), never the whole store.

A composition root (server.py, the CLI's commands) makes the roles over one connection
(ClickHouse: one adapter per role, adapters/clickhouse/store.py) or cuts one store that
answers them all (the memory store) into `StoreRoles`; it then hands each component the
fields it needs. A cut role is a `RoleView`: it answers its protocol's members and nothing
else, so a component that reaches for a method of another role fails at once with a
message naming its role, instead of quietly depending on the whole store.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any, Protocol

from mapservice.core.ports import (
    AnnotationReader,
    ChangeFeed,
    CommandReader,
    ConflictReader,
    HeatmapReader,
    HistoryStore,
    HistoryWriter,
    IncidentReader,
    LegacyQueries,
    RetentionKeeper,
    SnapshotKeeper,
    StoreAdmin,
    StoreSchema,
    TableExports,
    TimeTravelReader,
    VdaReader,
    WebhookRegistry,
)


@cache
def role_members(role: type) -> frozenset[str]:
    """The public names a role protocol declares, its bases' included (methods and
    attributes)."""
    names: set[str] = set()
    for klass in role.__mro__:
        if klass is Protocol or klass is object or not getattr(klass, "_is_protocol", False):
            continue
        names.update(n for n in vars(klass) if not n.startswith("_"))
        names.update(n for n in vars(klass).get("__annotations__", {}) if not n.startswith("_"))
    return frozenset(names)


class RoleView:
    """One role of a store: its protocol's members, looked up on the store when called
    (so a store whose method is replaced later is seen as it is); any other name is an
    AttributeError that names the role."""

    __slots__ = ("_members", "_role", "_store")
    _members: frozenset[str]
    _role: type
    _store: object

    def __init__(self, store: object, role: type) -> None:
        members = role_members(role)
        missing = sorted(m for m in members if not hasattr(store, m))
        if missing:
            raise TypeError(f"{type(store).__name__} is no {role.__name__}: it lacks {missing}")
        object.__setattr__(self, "_store", store)
        object.__setattr__(self, "_role", role)
        object.__setattr__(self, "_members", members)

    @property
    def role(self) -> type:
        return self._role

    def __getattr__(self, name: str) -> Any:
        # Only called for names not found on the view itself: the role's members.
        if name in self._members:
            return getattr(self._store, name)
        raise AttributeError(
            f"{name!r} is not part of the {self._role.__name__} role this component was given"
        )

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"a {self._role.__name__} role is read-only")

    def __dir__(self) -> list[str]:
        return sorted(self._members)

    def __repr__(self) -> str:
        return f"<{self._role.__name__} of {type(self._store).__name__}>"


def narrowed(store: object, role: type) -> Any:
    """`store` seen as `role` only (typed by the caller: a protocol class cannot be a
    type variable's value)."""
    return RoleView(store, role)


@dataclass(frozen=True, eq=False)
class StoreRoles:
    """Every role of one store, each on its own: what a composition root hands out, one
    field to each component that uses it. `exports` is None for a store that cannot run
    the analysts' table exports (only ClickHouse can)."""

    schema: StoreSchema
    writer: HistoryWriter
    history: TimeTravelReader
    snapshots: SnapshotKeeper
    retention: RetentionKeeper
    conflicts: ConflictReader
    annotations: AnnotationReader
    incidents: IncidentReader
    heatmaps: HeatmapReader
    commands: CommandReader
    vda: VdaReader
    webhooks: WebhookRegistry
    changes: ChangeFeed
    legacy: LegacyQueries
    admin: StoreAdmin
    exports: TableExports | None = None

    @classmethod
    def of(cls, store: HistoryStore | StoreRoles) -> StoreRoles:
        """The roles of a whole store, each a view that answers only its role (roles
        already made apart are returned as they are)."""
        if isinstance(store, StoreRoles):
            return store
        has_exports = all(hasattr(store, m) for m in role_members(TableExports))
        return cls(
            schema=narrowed(store, StoreSchema),
            writer=narrowed(store, HistoryWriter),
            history=narrowed(store, TimeTravelReader),
            snapshots=narrowed(store, SnapshotKeeper),
            retention=narrowed(store, RetentionKeeper),
            conflicts=narrowed(store, ConflictReader),
            annotations=narrowed(store, AnnotationReader),
            incidents=narrowed(store, IncidentReader),
            heatmaps=narrowed(store, HeatmapReader),
            commands=narrowed(store, CommandReader),
            vda=narrowed(store, VdaReader),
            webhooks=narrowed(store, WebhookRegistry),
            changes=narrowed(store, ChangeFeed),
            legacy=narrowed(store, LegacyQueries),
            admin=narrowed(store, StoreAdmin),
            exports=narrowed(store, TableExports) if has_exports else None,
        )
