"""Shared fixtures for the fast (broker-free) tests: a fixed clock, 2019 wire messages
(`wire`), event envelopes (`ev`), and the history stores: every adapter of the store port
behind one parametrized fixture (`store`), over one chDB engine per module (`chdb_dir`)."""

from __future__ import annotations

import itertools
import os
import shutil
import signal
import time
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
import pytest

from mapservice.adapters.clock import ManualClock
from mapservice.core.events import (
    ChunkUpdated,
    DeadLetter,
    Envelope,
    MapMetaSet,
    PoseReported,
    make_envelope,
)
from mapservice.core.wire2019 import Limits, content_hash, encode_pixels, format_timestamp
from mapservice.local.embedded import PORT_SLICE_ENV, sub_slice
from tests.fixtures.listings_2019 import listing_14, listing_16

if TYPE_CHECKING:
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.core.ports import HistoryStore


# The slice the run was started with, before a worker's own replaces it.
_RUN_PORT_SLICE = os.environ.get(PORT_SLICE_ENV)


def pytest_configure(config: pytest.Config) -> None:
    """On pytest-xdist's workers, each worker's stacks (and their children) choose ports
    from a slice of their own (of the run's slice, when it has one), so stacks started side
    by side never collide.

    A run started in the background by a shell without job control (`make test` runs the
    fast tests beside the `alone` tests) inherits SIGINT ignored, and Python then keeps it
    ignored: Ctrl-C would leave that run going, its servers with it. It gets Python's own
    handler back, so it stops as a run in the foreground does, its fixtures torn down."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    worker, count = (
        os.environ.get("PYTEST_XDIST_WORKER"),
        os.environ.get("PYTEST_XDIST_WORKER_COUNT"),
    )
    if worker and count and worker.removeprefix("gw").isdigit() and count.isdigit():
        os.environ[PORT_SLICE_ENV] = sub_slice(
            _RUN_PORT_SLICE, int(worker.removeprefix("gw")), int(count)
        )


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """A session that selects integration tests only (`-m "integration ..."`) does not import
    the modules that cannot hold one: importing and generating the thousands of fast tests
    only to deselect them cost every worker of every integration step its time."""
    if not str(config.option.markexpr).startswith("integration"):
        return None
    if collection_path.suffix != ".py" or not collection_path.name.startswith("test_"):
        return None
    return None if _may_hold_integration_tests(collection_path) else True


def pytest_deselected(items: list[pytest.Item]) -> None:
    """The fast session, which imports every module, checks the rule above held for each
    integration test it passed over: one marked some other way would otherwise be skipped
    by the integration steps without a word."""
    missed = sorted(
        {
            str(item.path)
            for item in items
            if item.get_closest_marker("integration") and not _may_hold_integration_tests(item.path)
        }
    )
    if missed:
        pytest.exit(
            "integration tests in modules that neither they nor a conftest.py above them "
            f"mark with `pytest.mark.integration` (the integration steps would not import them): {missed}",
            returncode=4,
        )


def _may_hold_integration_tests(module: Path) -> bool:
    """The module, or a conftest.py above it in tests/, names the marker."""
    tests = Path(__file__).parent
    places = [module] + [
        d / "conftest.py" for d in module.parents if d.is_relative_to(tests) and d != tests
    ]
    return any(
        place.is_file() and "mark.integration" in place.read_text(errors="replace")
        for place in places
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Modules with a `long` test first: pytest-xdist hands out whole modules in this order
    (`--dist loadfile`), so the parallel step does not end on one worker's long module."""
    long_modules = {item.path for item in items if item.get_closest_marker("long")}
    items.sort(key=lambda item: item.path not in long_modules)


# 2026-11-21T10:00:00Z: a fixed "now" so every test sees the same gateway clock.
NOW_MS = 1_795_255_200_000


@pytest.fixture(autouse=True)
def _hermetic_env(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """No MAPSERVICE_* variable of the developer's shell leaks into Settings() in fast tests
    (integration tests keep the environment they were started with), and the test
    client's host name is the apps' own."""
    if request.node.get_closest_marker("integration"):
        return
    for name in list(os.environ):
        if name.upper().startswith("MAPSERVICE_"):
            monkeypatch.delenv(name)
    # Starlette's TestClient sends Host: testserver, a name no deployment has: the fast
    # tests' apps take it as one of theirs (tests/api/test_host_check.py sends others).
    monkeypatch.setenv("MAPSERVICE_API_ALLOWED_HOSTS", '["testserver"]')


def librdkafka_clients(settle_s: float = 0.0, among: set[str] | None = None) -> set[str]:
    """This process's librdkafka clients, each by its one `rdk:main` thread's id (Linux
    lists threads in /proc; elsewhere none are counted), among the threads `among` (ids, as
    `thread_ids()` gives them) or all. Broker threads (`rdk:broker...`)
    are not counted: a client whose brokers have been gone for a while bootstraps again,
    with new broker threads, at any moment, so an integration test's leftover client would
    otherwise be blamed on whatever fast test runs then. A thread is named by its creator's
    name until it names itself, so a broker thread just made reads `rdk:main` for a moment:
    with `settle_s`, only threads still `rdk:main` that much later are counted."""
    clients = _threads_named("rdk:main", among)
    if settle_s and clients:
        time.sleep(settle_s)
        clients &= _threads_named("rdk:main", clients)
    return clients


def thread_ids() -> set[str]:
    """The ids of this process's threads (none where /proc does not list them)."""
    try:
        return set(os.listdir("/proc/self/task"))
    except OSError:
        return set()


def _threads_named(name: str, among: set[str] | None = None) -> set[str]:
    found = set()
    for task in thread_ids() if among is None else among:
        try:
            with open(f"/proc/self/task/{task}/comm") as comm:
                if comm.read().strip() == name:
                    found.add(task)
        except OSError:  # the thread ended meanwhile
            continue
    return found


@pytest.fixture(autouse=True)
def _kafka_clients_closed(request: pytest.FixtureRequest) -> Iterator[None]:
    """A fast test closes every librdkafka client it made. One left open (or left to the
    garbage collector, when a callback refers back to it) keeps dialling its unreachable
    broker from its own threads, logging each failure, into the tests that follow.
    A client the test made has a thread the test made, so only the threads new since the
    test began are read: reading the name of each of a worker's threads (chDB's pool among
    them) before and after each of thousands of tests cost more than most of the tests."""
    if request.node.get_closest_marker("integration"):
        yield
        return
    before = thread_ids()
    yield
    left = librdkafka_clients(among=thread_ids() - before)
    if left:
        left = librdkafka_clients(settle_s=0.05, among=left)
    if left:
        pytest.fail(f"{len(left)} librdkafka clients still run: close the Kafka clients made here")


@pytest.fixture
def now_ms() -> int:
    return NOW_MS


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(NOW_MS)


@pytest.fixture
def limits() -> Limits:
    return Limits()


@dataclass
class Wire:
    """Builds 2019 MQTT payloads (listings 14 and 16) around a gateway clock."""

    now_ms: int

    def ts(self, offset_ms: int = 0) -> str:
        """A 2019-style timestamp (no zone, UTC) `offset_ms` from now."""
        return format_timestamp(self.now_ms + offset_ms)

    b64z = staticmethod(encode_pixels)

    def chunk_doc(self, **overrides) -> dict:
        """Listing 14, field for field, with real 100 x 100 pixels and a current timestamp."""
        return listing_14(self.ts(), bytes([205]) * 10_000, **overrides)

    def chunk(self, **overrides) -> bytes:
        return msgspec.json.encode(self.chunk_doc(**overrides))

    def pose_doc(self, **overrides) -> dict:
        """Listing 16 as printed (integers, string flags), with a current timestamp."""
        return listing_16(self.ts(), **overrides)

    def pose(self, **overrides) -> bytes:
        return msgspec.json.encode(self.pose_doc(**overrides))


@pytest.fixture
def wire(now_ms: int) -> Wire:
    return Wire(now_ms)


# --- events for store and API tests ---------------------------------------------------


def pose_event(
    robot_id: str, t_ms: int, x: float = 1.0, y: float = 2.0, *, receive_lag_ms: int = 40, **fields
) -> Envelope:
    payload = PoseReported(
        position=(x, y, 0.0),
        orientation=(0.0, 0.0, 0.0, 1.0),
        battery_level=fields.pop("battery_level", 80.0),
        **fields,
    )
    return make_envelope(robot_id, t_ms, t_ms + receive_lag_ms, payload)


def chunk_event(
    robot_id: str,
    t_ms: int,
    row: int = 0,
    column: int = 0,
    pixels: bytes = bytes(100 * 100),
    *,
    width: int = 100,
    height: int = 100,
    receive_lag_ms: int = 25,
) -> Envelope:
    payload = ChunkUpdated(
        row=row,
        column=column,
        width=width,
        height=height,
        data=zlib.compress(pixels),
        content_hash=content_hash(pixels),
    )
    return make_envelope(robot_id, t_ms, t_ms + receive_lag_ms, payload)


def meta_event(
    t_ms: int, chunk_rows: int = 4, chunk_cols: int = 5, robot_id: str = "admin"
) -> Envelope:
    payload = MapMetaSet(
        width=chunk_cols * 100,
        height=chunk_rows * 100,
        chunk_width=100,
        chunk_height=100,
        chunk_rows=chunk_rows,
        chunk_cols=chunk_cols,
        comment=f"meta at {t_ms}",
        resolution=0.05,
        origin=(-1.5, 2.0, 0.0),
    )
    return make_envelope(robot_id, t_ms, t_ms, payload)


def dead_letter(
    reason: str = "not_json", payload: bytes = b"{oops", t_ms: int = NOW_MS
) -> DeadLetter:
    return DeadLetter(
        reason=reason,
        detail="test",
        mqtt_topic="iot/chunks/create",
        payload=payload,
        receive_time_ms=t_ms,
        gateway="test-gw",
    )


@dataclass(frozen=True)
class EventFactory:
    pose = staticmethod(pose_event)
    chunk = staticmethod(chunk_event)
    meta = staticmethod(meta_event)
    dead_letter = staticmethod(dead_letter)


@pytest.fixture
def ev() -> EventFactory:
    """Builders of envelopes and dead letters (`ev.pose(...)`, `ev.chunk(...)`, ...)."""
    return EventFactory()


# --- the history stores ---------------------------------------------------------------
# Every adapter of the HistoryStore port, as the `store` fixture's parameters: the memory
# twin, ClickHouseStore on embedded chDB, and ClickHouseStore over ClickHouse's HTTP
# interface (the split deployment's path: `mapservice clickhouse-server`'s app over the
# module's chDB, served from this process). A module's contract tests take `store` and run
# over all three; a module needing a store of one kind calls `open_store(kind, ...)`.
STORE_KINDS = ("memory", "clickhouse", "clickhouse-http")
_store_databases = itertools.count()


# Each module's chDB holds one migrated database, the template that `clone_migrated` copies.
SCHEMA_TEMPLATE = "schema_template"
_templates: dict[Path, ClickHouseStore] = {}


@pytest.fixture(scope="session")
def _migrated_engine(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The files of a closed chDB engine that holds the migrated template and nothing else,
    made once per test process: each module's engine starts as a copy of them (a tenth of
    a second) instead of running the migrations again (seconds under a test run's load).
    The engine's links between its directories are relative, so a copy is an engine of its
    own."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore

    path = tmp_path_factory.mktemp("chdb-template") / "ch"
    template = ClickHouseStore(f"chdb://{path}", database=SCHEMA_TEMPLATE)
    template.migrate()
    template.close()
    return path


@pytest.fixture(scope="module")
def chdb_dir(tmp_path_factory: pytest.TempPathFactory, _migrated_engine: Path) -> Iterator[Path]:
    """One chDB engine for the module, kept open by a migrated template store and closed at
    the module's end: chDB runs one engine per process, so the next module may then open its
    own. Each store the module opens is a database of its own in it (an empty history).
    The engine is a copy of the process's migrated one; the template's migrate() checks it
    finds every migration applied, checksums included."""
    from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION
    from mapservice.adapters.clickhouse.store import ClickHouseStore

    path = tmp_path_factory.mktemp("chdb") / "ch"
    shutil.copytree(_migrated_engine, path, symlinks=True)
    template = ClickHouseStore(f"chdb://{path}", database=SCHEMA_TEMPLATE)
    assert template.migrate() == SCHEMA_VERSION
    _templates[path] = template
    yield path
    del _templates[path]
    template.close()


def clone_migrated(chdb_dir: Path, database: str) -> None:
    """Creates `database` in the module's chDB as migrate() leaves a new one: the template's
    tables and views, and its log of applied migrations (so the store's own migrate() then
    finds every migration applied, checksums included). About 40 statements instead of the
    170 of the migrations (a chDB statement costs milliseconds; every store test makes a
    database). tests/mapservice/adapters/clickhouse/test_migrations.py checks that a clone
    has exactly the schema the migrations make."""
    from mapservice.adapters.clickhouse.migrations import MIGRATION_LOCK

    template = _templates[chdb_dir]
    source, c = template.database, template.client
    objects = c.query(
        "SELECT name, engine, create_table_query FROM system.tables "
        "WHERE database = {d:String} AND name != {lock:String}",
        parameters={"d": source, "lock": MIGRATION_LOCK},
    ).result_rows
    c.command(f"CREATE DATABASE {database}")
    # Tables first; a view may read another view, so views go once what they read exists.
    pending = [
        ddl.replace(f"{source}.", f"{database}.")
        for _, engine, ddl in sorted(objects, key=lambda o: o[1] in ("View", "MaterializedView"))
    ]
    while pending:
        failed = []
        for ddl in pending:
            try:
                c.command(ddl)
            except Exception:  # a view over one not created yet: again after the others
                if not ddl.startswith(("CREATE VIEW", "CREATE MATERIALIZED VIEW")):
                    raise
                failed.append(ddl)
        if len(failed) == len(pending):
            c.command(failed[0])  # no progress: raise its error
        pending = failed
    c.command(f"INSERT INTO {database}.schema_migrations SELECT * FROM {source}.schema_migrations")


@pytest.fixture(scope="module")
def clickhouse_http(chdb_dir: Path) -> Iterator[str]:
    """The ClickHouse HTTP interface over the module's chDB (read-write for `default`): its URL."""
    from mapservice.sql.chdb_engine import ChdbEngine
    from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
    from tests.mapservice.sql.serving import ServedApp

    engine = ChdbEngine(chdb_dir)
    app = clickhouse_http_app(engine, [SqlUser("default", "", read_only=False)])
    with ServedApp(app) as served:
        yield served.url
    engine.close()


@pytest.fixture
def open_store(request: pytest.FixtureRequest) -> Callable[..., HistoryStore]:
    """`open_store(kind, database=None, **options)`: a new store of `kind` (STORE_KINDS), not
    yet migrated. ClickHouse kinds open `database` (default: a new one) in the module's
    chDB with ClickHouseStore's `options`; the memory twin takes `retention_days` only."""
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.testing.memory_store import MemoryStore

    def open_(kind: str, database: str | None = None, **options: int) -> HistoryStore:
        if kind == "memory":
            return MemoryStore(**{k: v for k, v in options.items() if k == "retention_days"})
        database = database or f"store_{next(_store_databases)}"
        if kind == "clickhouse":
            dsn = f"chdb://{request.getfixturevalue('chdb_dir')}"
        elif kind == "clickhouse-http":
            dsn = request.getfixturevalue("clickhouse_http")
        else:
            raise ValueError(f"unknown store kind {kind!r}; one of {STORE_KINDS}")
        return ClickHouseStore(dsn, database=database, **options)

    return open_


@pytest.fixture
def t0() -> int:
    """A whole second an hour ago: inside the retention, so no ClickHouse TTL drops the rows."""
    import time

    return (time.time_ns() // 1_000_000 // 1000) * 1000 - 3_600_000


def sparse_snapshots(store, every_ms: int = 6 * 3_600_000) -> None:
    """Makes a ClickHouse store snapshot every `every_ms` (6 h) instead of every 10 minutes,
    before its first snapshot: a test that runs days of history through the retention then
    builds tens of snapshots, not thousands (each a few chDB statements). No answer depends
    on the interval: a read folds the events after the newest snapshot before its instant.
    The memory twin keeps no snapshots."""
    if hasattr(store, "snapshot_every_ms"):
        store.snapshot_every_ms = every_ms


@pytest.fixture(params=STORE_KINDS)
def store(
    request: pytest.FixtureRequest, open_store: Callable[..., HistoryStore]
) -> Iterator[HistoryStore]:
    """An empty, migrated store of each kind (a module's own `store` fixture overrides it)."""
    s = open_store(request.param)
    if request.param != "memory":
        clone_migrated(request.getfixturevalue("chdb_dir"), s.database)
    s.migrate()
    yield s
    s.close()


# --- a broker -----------------------------------------------------------------------------


@pytest.fixture(scope="session")
def apache_kafka(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """One Apache Kafka node (from the Maven jars, as `mapservice up` runs it) for the
    session's tests that need a broker and nothing else (each uses topic names of its own);
    its bootstrap address. A stack starts its own."""
    from mapservice.local import embedded, kafka_broker

    if kafka_broker.java_binary() is None:
        pytest.fail("no Java runtime for Apache Kafka (`make system-deps` installs it)")
    root = tmp_path_factory.mktemp("apache-kafka")
    node = kafka_broker.node_for(root, embedded.free_port())
    proc = kafka_broker.start_kafka(node, open(root / "kafka.log", "ab"))
    yield f"127.0.0.1:{node.port}"
    kafka_broker.stop_process_group(proc)
