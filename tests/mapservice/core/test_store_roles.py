"""A store cut into its roles (mapservice/core/store_roles.py): each role answers its own
protocol's members, looked up on the store when used, and refuses every other name."""

from __future__ import annotations

import dataclasses

import pytest

from mapservice.core import ports
from mapservice.core.store_roles import RoleView, StoreRoles, narrowed, role_members
from mapservice.testing.memory_store import MemoryStore

FIELDS = {f.name: f for f in dataclasses.fields(StoreRoles)}
ROLE_OF_FIELD = {
    name: f.type if isinstance(f.type, type) else getattr(ports, str(f.type).split(" |")[0])
    for name, f in FIELDS.items()
}


def _roles() -> StoreRoles:
    return StoreRoles.of(MemoryStore())


@pytest.mark.parametrize("field", sorted(n for n in FIELDS if n != "exports"))
def test_each_role_answers_its_own_members_and_no_other_roles(field) -> None:
    """For every role and every member of every other role: the role's own are there,
    another role's (not shared) are an AttributeError naming the role."""
    role = ROLE_OF_FIELD[field]
    view = getattr(_roles(), field)
    assert isinstance(view, RoleView) and view.role is role
    own = role_members(role)
    for name in own:
        assert hasattr(view, name), name
    others = {m for r in ports.HistoryStore.__mro__ for m in _members_of(r)} - own
    assert others, "every role leaves something out"
    for name in others:
        with pytest.raises(AttributeError, match=f"not part of the {role.__name__} role"):
            getattr(view, name)


def _members_of(klass) -> frozenset[str]:
    if getattr(klass, "_is_protocol", False) and klass.__module__ == ports.__name__:
        return role_members(klass)
    return frozenset()


def test_the_roles_together_are_the_whole_store() -> None:
    """Every member of HistoryStore is in exactly the roles that declare it: cutting the
    store loses nothing."""
    covered = set().union(*(role_members(ROLE_OF_FIELD[n]) for n in FIELDS if n != "exports"))
    assert covered == role_members(ports.HistoryStore)


def test_a_role_calls_the_store_as_it_is_when_called() -> None:
    """A method replaced on the store after it was cut (a test's fault injection) is the
    one the role calls."""
    store = MemoryStore()
    roles = StoreRoles.of(store)
    store.counts = lambda: "replaced"  # type: ignore[method-assign]
    assert roles.admin.counts() == "replaced"


def test_a_role_cannot_be_written_to() -> None:
    view = _roles().writer
    with pytest.raises(AttributeError, match="read-only"):
        view.append = None  # type: ignore[method-assign]


def test_a_store_without_a_role_is_refused_naming_what_it_lacks() -> None:
    class NoWriter:
        def migrate(self) -> int:
            return 1

    with pytest.raises(TypeError, match=r"NoWriter is no HistoryWriter: it lacks \['append'"):
        narrowed(NoWriter(), ports.HistoryWriter)


def test_table_exports_only_for_a_store_that_has_them() -> None:
    """The memory store has no SQL: no exports role (the route answers 501); a store with
    `export_query` and `database` gets one."""
    assert _roles().exports is None

    class Exporting(MemoryStore):
        database = "db"

        def export_query(self, sql: str, parameters: dict, fmt: str) -> bytes:
            return b"rows"

    exports = StoreRoles.of(Exporting()).exports
    assert exports is not None and exports.export_query("", {}, "CSV") == b"rows"
    assert exports.database == "db"
    with pytest.raises(AttributeError):
        exports.counts  # noqa: B018
