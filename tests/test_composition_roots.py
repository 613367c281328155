"""No component receives the whole store: the composition roots (the processors',
processors/composition.py, and the API's, api/composition.py and api/app.py) are handed
the store and give each part only the roles it uses (mapservice/core/store_roles.py).

Three views of one rule, each over whatever the roots build, so a part added later is
covered without being named here:
- every object the processors' root constructs or calls is given no whole store (nor
  anything that holds one);
- every argument an API route is handed through its dependencies is no whole store;
- nothing the composed parts or the API app hold leads to the whole store, except
  through a role that answers only its own protocol.

"Whole store" is the store object handed to the root, and also anything that answers the
methods of more than one role: a second store made by a root would be caught too.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import inspect
import types
from collections.abc import Iterator
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.routing import APIRoute, APIWebSocketRoute
from starlette.requests import Request
from starlette.websockets import WebSocket

import mapservice.processors.composition as processors_composition
from mapservice.api.access import all_routes
from mapservice.core import ports
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

# Every role protocol of the store: an object answering all of one role and part of no
# other is a role; one answering two roles in full is a whole store.
ROLES = [
    ports.StoreSchema,
    ports.HistoryWriter,
    ports.TimeTravelReader,
    ports.SnapshotKeeper,
    ports.RetentionKeeper,
    ports.ConflictReader,
    ports.AnnotationReader,
    ports.IncidentReader,
    ports.HeatmapReader,
    ports.CommandReader,
    ports.VdaReader,
    ports.WebhookRegistry,
    ports.ChangeFeed,
    ports.LegacyQueries,
    ports.StoreAdmin,
]


def test_the_role_list_here_is_every_role_of_the_whole_store() -> None:
    """HistoryStore's bases are the roles above: a new role is checked as soon as it exists."""
    bases = {b for b in ports.HistoryStore.__mro__[1:] if b.__module__ == ports.__name__}
    assert bases == set(ROLES)


def members(role: type) -> set[str]:
    """The public names a role protocol declares, its bases' included."""
    names: set[str] = set()
    for klass in role.__mro__:
        if getattr(klass, "_is_protocol", False) and klass.__module__ == ports.__name__:
            names.update(n for n in vars(klass) if not n.startswith("_"))
    return names


def roles_answered(obj: object) -> list[str]:
    """The roles whose every member `obj` has."""
    if isinstance(obj, type | types.ModuleType):
        return []
    return [r.__name__ for r in ROLES if all(hasattr(obj, m) for m in members(r))]


def is_whole_store(obj: object, store: object) -> bool:
    return obj is store or len(roles_answered(obj)) > 1


def _ours(obj: object) -> bool:
    module = getattr(type(obj), "__module__", "") or ""
    return module.startswith(("mapservice", "tests"))


def _children(obj: object) -> Iterator[tuple[str, object]]:
    """What `obj` holds: its attributes (ours only: third-party objects are not walked),
    container items, and what a function or method closes over."""
    if len(roles_answered(obj)) == 1:
        return  # a role: how its adapter reaches the data behind it is the adapter's business
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield f"[{k!r}]", v
    elif isinstance(obj, list | tuple | set | frozenset):
        for i, v in enumerate(obj):
            yield f"[{i}]", v
    elif isinstance(obj, types.MethodType):
        yield ".__self__", obj.__self__
        yield ".__func__", obj.__func__
    elif isinstance(obj, functools.partial):
        yield ".func", obj.func
        yield ".args", obj.args
        yield ".keywords", obj.keywords
    elif isinstance(obj, types.FunctionType):
        for name, cell in zip(obj.__code__.co_freevars, obj.__closure__ or (), strict=True):
            try:
                yield f"<closure {name}>", cell.cell_contents
            except ValueError:  # an empty cell
                continue
    elif _ours(obj) and not isinstance(obj, type):
        if dataclasses.is_dataclass(obj):
            for f in dataclasses.fields(obj):
                yield f".{f.name}", getattr(obj, f.name, None)
        for name, value in getattr(obj, "__dict__", {}).items():
            yield f".{name}", value
        for name in getattr(type(obj), "__slots__", ()):
            if hasattr(obj, name):
                yield f".{name}", getattr(obj, name)


def paths_to_whole_store(root: object, store: object, where: str) -> list[str]:
    """Every path from `root` to the whole store, walking what our objects hold."""
    found, seen, todo = [], set(), [(where, root)]
    while todo:
        path, obj = todo.pop()
        if id(obj) in seen or obj is None or isinstance(obj, str | bytes | int | float):
            continue
        seen.add(id(obj))
        if is_whole_store(obj, store):
            found.append(f"{path}: {type(obj).__name__} ({', '.join(roles_answered(obj))})")
            continue
        todo.extend((path + step, child) for step, child in _children(obj))
    return found


# --- the processors -----------------------------------------------------------------------


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(kafka_bootstrap="127.0.0.1:1", mqtt_url="mqtt://127.0.0.1:1", data_dir=tmp_path)


def test_no_part_the_processors_build_is_handed_the_whole_store(settings, monkeypatch) -> None:
    """Each class and function the processors' root calls is recorded with its arguments:
    none is the store, or holds it (the sink gets the writer, the views their readers and
    the writer, the snapshot timer the snapshot and retention keepers)."""
    store = MemoryStore()
    calls: list[tuple[str, dict[str, Any]]] = []
    for name, value in list(vars(processors_composition).items()):
        if name.startswith("_") or not callable(value) or name == "compose_processors":
            continue
        # The parts: the processors' and the adapters' (the core's pure helpers, such as
        # the one that cuts the store into roles, are no components).
        if not getattr(value, "__module__", "").startswith(
            ("mapservice.processors", "mapservice.adapters")
        ):
            continue

        def recorded(*args, _name=name, _real=value, **kwargs):
            calls.append((_name, {**{f"#{i}": a for i, a in enumerate(args)}, **kwargs}))
            return _real(*args, **kwargs)

        monkeypatch.setattr(processors_composition, name, recorded)
    parts = processors_composition.compose_processors(settings, store)
    try:
        called = {name for name, _ in calls}
        # The parts that use the store are among those recorded (else this test sees nothing).
        assert {"HistorySink", "LiveViews", "snapshot_timer"} <= called, called
        handed = [
            found
            for name, arguments in calls
            for found in paths_to_whole_store(arguments, store, name)
        ]
        assert handed == [], "\n".join(handed)
        assert paths_to_whole_store(parts, store, "processors") == []
    finally:
        parts.store_thread.close()
        parts.views.close()


# --- the API ------------------------------------------------------------------------------


def _api_settings(tmp_path) -> Settings:
    """No analyst password: no analysts' SQL, so no ClickHouse engine is opened."""
    return Settings(
        mode="production",
        admin_token="t" * 32,
        clickhouse_dsn="http://127.0.0.1:1",
        clickhouse_password="p" * 16,
        kafka_bootstrap="127.0.0.1:1",
        data_dir=tmp_path,
        api_host="127.0.0.1",
        api_port=18_998,
    )


def _composed_app(tmp_path, store) -> FastAPI:
    from mapservice.api.composition import compose_api

    async def build():
        return await compose_api(
            _api_settings(tmp_path),
            store,
            readiness={},
            liveness={},
            advisory={},
            history_status=None,
        )

    api = asyncio.run(build())
    api.publisher.close()
    return api.app


class _Unresolved(Exception):
    """A dependency that needs the request's data (a token, a query parameter)."""


async def _resolve(dependant, connection, cache: dict) -> dict[str, object]:
    """The values of `dependant`'s sub-dependencies that need nothing from the request but
    the connection itself (the app's parts): those a route is handed from the app."""
    values: dict[str, object] = {}
    for sub in dependant.dependencies:
        try:
            value = await _call(sub, connection, cache)
        except _Unresolved:
            continue
        if sub.name is not None:
            values[sub.name] = value
    return values


async def _call(sub, connection, cache: dict) -> object:
    key = sub.call
    if key in cache:
        return cache[key]
    if (
        sub.query_params
        or sub.header_params
        or sub.cookie_params
        or sub.path_params
        or sub.body_params
    ):
        raise _Unresolved
    kwargs: dict[str, object] = {}
    for sub_sub in sub.dependencies:
        value = await _call(sub_sub, connection, cache)
        if sub_sub.name is not None:
            kwargs[sub_sub.name] = value
    for name in (sub.request_param_name, sub.websocket_param_name, sub.http_connection_param_name):
        if name is not None:
            kwargs[name] = connection
    try:
        result = sub.call(**kwargs)
        if inspect.isawaitable(result):
            result = await result
    except Exception as exc:  # a check of the caller (a token) refuses the empty request
        raise _Unresolved from exc
    cache[key] = result
    return result


def _connection(app: FastAPI, websocket: bool):
    scope = {
        "type": "websocket" if websocket else "http",
        "app": app,
        "path": "/",
        "headers": [],
        "query_string": b"",
        "method": "GET",
    }
    if websocket:
        return WebSocket(scope, receive=None, send=None)  # type: ignore[arg-type]
    return Request(scope)


def handed_to_routes(app: FastAPI) -> dict[str, dict[str, object]]:
    """Per route, the arguments its dependencies hand it from the app."""
    out = {}
    for route in all_routes(app):
        if not isinstance(route, APIRoute | APIWebSocketRoute):
            continue
        connection = _connection(app, isinstance(route, APIWebSocketRoute))
        methods = ",".join(sorted(getattr(route, "methods", None) or {"WEBSOCKET"}))
        out[f"{methods} {route.path}"] = asyncio.run(_resolve(route.dependant, connection, {}))
    return out


def test_no_api_route_is_handed_the_whole_store(tmp_path) -> None:
    """Every route's arguments from the app are resolved as FastAPI would: each is one role
    of the store (or no store at all), never the store or the app's whole context."""
    store = MemoryStore()
    app = _composed_app(tmp_path, store)
    handed = handed_to_routes(app)
    found = [
        path
        for route, arguments in handed.items()
        for name, value in arguments.items()
        for path in paths_to_whole_store(value, store, f"{route} {name}")
    ]
    assert found == [], "\n".join(found)
    roles_handed = {
        role
        for arguments in handed.values()
        for v in arguments.values()
        for role in roles_answered(v)
    }
    # The routes do read the store (so the resolution above reached what they are handed).
    assert {"TimeTravelReader", "LegacyQueries", "StoreAdmin", "AnnotationReader"} <= roles_handed
    whole = [
        f"{route} {name}: {type(v).__name__}"
        for route, arguments in handed.items()
        for name, v in arguments.items()
        if type(v).__name__ in ("ApiContext", "StoreRoles")
    ]
    assert whole == [], "routes handed the app's parts whole:\n" + "\n".join(whole)


def test_the_api_app_holds_the_store_only_by_role(tmp_path) -> None:
    """What the app keeps for its routes and middlewares leads to the store only through
    roles: no route, middleware or cache can reach for the store as a whole."""
    store = MemoryStore()
    app = _composed_app(tmp_path, store)
    state = dict(vars(app.state).get("_state", {}))
    assert state, "the app keeps its parts in app.state"
    assert paths_to_whole_store(state, store, "app.state") == []
