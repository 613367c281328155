"""The SQL engine over the embedded chDB of this process (the one process that may open
the data directory: `mapservice serve` or `mapservice clickhouse-server`).

Each statement runs on a chDB connection handle of its own kind:
- read-write statements on a small pool of handles; a statement's settings are `SET` on
  the handle first and reset to `DEFAULT` afterwards, so no request sees another's;
- inserts (the processors storing the history) and `SELECT 1` (readiness) on pools of
  their own: a few long reads (the API's exports, run by the service's user) hold every
  handle of the first pool, and the history would wait behind them;
- read-only statements on a fresh handle: the request's settings, then the limits, then
  `readonly = 1` (which the engine enforces and nobody can lift on that handle); closed
  afterwards (about 1 ms). clickhouse-local, under chDB, does not confine the scalar
  `file()` to `user_files_path` nor `url()` to allowed hosts: for those the analysts'
  allow-list (read_only.py) is the only line here; a ClickHouse server enforces both.
"""

from __future__ import annotations

import os
import queue
import re
import shutil
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

from mapservice.sql.engine import SqlError, SqlRequest, SqlResult, output_format
from mapservice.sql.settings_policy import apply_read_only

_NOT_ENOUGH_SPACE = 243
_PART_FILES_BYTES = 1 << 20

_SETTING_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
# SET and USE only change the session, and the HTTP interface here has none (like a
# server asked without session_id): they succeed and change nothing for later requests.
_SESSION_ONLY = re.compile(r"^\s*(SET|USE)\s", re.IGNORECASE)


def _quote(value: str) -> str:
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _identifier(name: str) -> str:
    return "`" + name.replace("\\", "\\\\").replace("`", "\\`") + "`"


def _setting_name(name: str) -> str:
    if not _SETTING_NAME.match(name):
        raise SqlError(f"Setting name {name!r} is not valid", 115)
    return name


class _Handle:
    def __init__(self, path: str):
        import chdb  # the embedded extra; a production process never opens chDB

        self.conn = chdb.connect(path)
        self.database: str | None = None

    def run(self, sql: str, fmt: str = "TabSeparated", params: dict[str, str] | None = None):
        try:
            return self.conn.query(sql, fmt, params=params or {})
        except Exception as exc:  # chDB raises RuntimeError with the ClickHouse text
            raise SqlError(str(exc).strip()) from exc

    def use(self, database: str | None) -> None:
        if database and database != self.database:
            self.run(f"USE {_identifier(database)}")
            self.database = database

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:  # closing twice or after an engine error: nothing left to free
            pass


INSERT_HANDLES = 2
_PING = re.compile(r"^\s*SELECT\s+1\s*;?\s*$", re.IGNORECASE)


class _Lane:
    """Up to `size` handles, opened when first needed; a caller beyond waits for one."""

    def __init__(self, size: int) -> None:
        self.size, self.opened = size, 0
        self.queue: queue.Queue[_Handle] = queue.Queue()
        self._lock = threading.Lock()

    def take(self, path: str) -> _Handle:
        try:
            return self.queue.get_nowait()
        except queue.Empty:
            with self._lock:
                grow = self.opened < self.size
                if grow:
                    self.opened += 1
            return _Handle(path) if grow else self.queue.get()


class ChdbEngine:
    """`SqlEngine` over chDB at `path`."""

    def __init__(
        self, path: str | Path, pool_size: int = 4, read_only_settings: dict[str, str] | None = None
    ):
        if "://" in str(path) and not str(path).startswith("chdb://"):
            raise ValueError(f"{path} is not a chDB directory (chdb:///dir or a path)")
        self.path = str(Path(str(path).removeprefix("chdb://")).resolve())
        self.read_only_settings = dict(read_only_settings or {})
        self._lanes = {
            "statements": _Lane(pool_size),
            "inserts": _Lane(INSERT_HANDLES),
            "ping": _Lane(1),
        }
        # Beside the data, not in the system's temporary directory: a process ended by a
        # signal never closes its engine, and left one empty directory there per start.
        self._inserts = Path(f"{self.path}-inserts")

    # --- handles -----------------------------------------------------------------

    @contextmanager
    def _pooled(self, lane: str = "statements"):
        pool = self._lanes[lane]
        handle = pool.take(self.path)
        try:
            yield handle
        finally:
            pool.queue.put(handle)

    @contextmanager
    def _fresh(self, settings: dict[str, str]):
        """A handle of its own with `settings` set in their order (`readonly` last: from then
        on the engine refuses writes and any change of a setting on it); closed at the end."""
        handle = _Handle(self.path)
        try:
            if settings:  # one SET: its assignments apply in their order
                handle.run(
                    "SET "
                    + ", ".join(f"{_setting_name(k)} = {_quote(v)}" for k, v in settings.items())
                )
            yield handle
        finally:
            handle.close()

    @contextmanager
    def _handle_for(self, request: SqlRequest, lane: str = "statements"):
        asked_readonly = request.settings.get("readonly", "0") not in ("", "0")
        if request.read_only or asked_readonly:
            # A read-only user: its settings (the protocol let only the settings policy's
            # through), then the limits, then readonly = 1, so neither can be lifted. A
            # writer asking for readonly (a server's client) gets its settings applied
            # first and readonly last, as a server applies a request's settings.
            if request.read_only:
                settings = apply_read_only(request.settings, self.read_only_settings)
            else:
                settings = {k: v for k, v in request.settings.items() if k != "readonly"}
                settings["readonly"] = request.settings["readonly"]
            with self._fresh(settings) as handle:
                handle.use(request.database)
                yield handle
            return
        with self._pooled(lane) as handle:
            applied: list[str] = []
            try:
                for name, value in request.settings.items():
                    handle.run(f"SET {_setting_name(name)} = {_quote(value)}")
                    applied.append(name)
                handle.use(request.database)
                yield handle
            finally:
                for name in applied:
                    handle.run(f"SET {name} = DEFAULT")

    # --- SqlEngine ------------------------------------------------------------------

    def execute(self, request: SqlRequest) -> SqlResult:
        fmt = output_format(request.sql, request.default_format)
        lane = "ping" if _PING.match(request.sql) and not request.settings else "statements"
        with self._handle_for(request, lane) as handle:
            if _SESSION_ONLY.match(request.sql):
                return SqlResult(b"", fmt)
            result = handle.run(request.sql, request.default_format, request.params)
            return SqlResult(result.bytes() or b"", fmt)

    def insert(self, target: str, fmt: str, data: bytes, request: SqlRequest) -> SqlResult:
        if request.read_only:
            raise SqlError("Cannot execute query in readonly mode", 164)
        # chDB has no request body: the rows go through a private file (as clickhouse-connect's
        # own chDB backend does). `.bin` keeps chDB from guessing a compression by extension.
        self._inserts.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(suffix=".bin", dir=self._inserts)
        try:
            with os.fdopen(fd, "wb") as file:
                file.write(data)
            with self._handle_for(request, "inserts") as handle:
                try:
                    handle.run(f"INSERT INTO {target} FROM INFILE {_quote(name)} FORMAT {fmt}")
                except SqlError as exc:
                    raise self._out_of_space(exc, len(data)) from exc
            return SqlResult(b"", fmt)
        finally:
            os.unlink(name)

    def _out_of_space(self, exc: SqlError, size: int) -> SqlError:
        """A failed insert on a disk too full to hold it, said as ClickHouse says it.

        A server reserves a part's space first and refuses with NOT_ENOUGH_SPACE; the
        embedded engine may get as far as writing the part and fail on whichever file the
        disk refused (CANNOT_READ_ALL_DATA, CANNOT_WRITE_TO_FILE_DESCRIPTOR, ...), which
        tells an operator nothing. With less free space than the rows (twice, compressed
        or not, plus a MiB for the part's files), the disk is the cause."""
        try:
            free = shutil.disk_usage(self.path).free
        except OSError:
            return exc
        if free >= 2 * size + _PART_FILES_BYTES or exc.code == _NOT_ENOUGH_SPACE:
            return exc
        return SqlError(
            f"Cannot write the inserted rows: {free} bytes free on the disk of {self.path} "
            f"for {size} bytes of rows; the engine said: {' '.join(str(exc).split())[:300]} "
            "(NOT_ENOUGH_SPACE)",
            _NOT_ENOUGH_SPACE,
        )

    def ping(self) -> bool:
        try:
            with self._pooled("ping") as handle:
                return str(handle.run("SELECT 1")).strip() == "1"
        except SqlError:
            return False

    def close(self) -> None:
        for pool in self._lanes.values():
            while True:
                try:
                    pool.queue.get_nowait().close()
                except queue.Empty:
                    break
        try:
            self._inserts.rmdir()
        except OSError:
            pass
