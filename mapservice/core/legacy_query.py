"""The 2019 query strings of GET /api/chunk-service/chunks and /api/coordinate-service/robots.

Pure: a mapping of query parameters in, a frozen query object (or a `QueryError` whose
message says what to fix) out, plus the filter/sort/page fold both the in-memory store
and the `latest` paths use. Decisions where the 2019 document is vague or unsafe:

- `sort` is `field:direction[,field:direction...]` over a whitelist; nothing the client
  sends reaches SQL as text. The identity columns are always appended as tie-breakers,
  so `skip` pages are stable.
- `limit` defaults to 10 and is at most MAX_LIMIT; `skip + limit` is at most MAX_WINDOW.
  Both are Elasticsearch's `index.max_result_window` (10,000), the bound every 2019
  client already lived with; page further back in time with `updatedBefore`.
- Times are ISO 8601 (no zone means UTC) or epoch milliseconds. `updatedSince` is
  inclusive and `updatedBefore` exclusive, so consecutive windows neither overlap nor
  leave gaps.
- `latest=true` is the map (robots) at an instant: just before `updatedBefore`, or now.
  The other filters then select among those winners, as 2019's `*-latest` indices did.
- Unknown parameters are ignored; a malformed known one is a `QueryError`.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from operator import attrgetter
from typing import Any, Literal, TypeVar

import msgspec

from mapservice.core.wire2019 import parse_query_instant, parse_timestamp

DEFAULT_LIMIT = 10
MAX_LIMIT = 10_000
MAX_WINDOW = 10_000
MAX_SORT_KEYS = 4
CHUNK_TYPES = ("pgm_base64_compressed", "png")

# 2019 sort field -> attribute of ChunkRow / PoseRow. The store maps these to columns.
CHUNK_SORT_FIELDS = {"timestamp": "ts_ms", "row": "row", "column": "column", "robotId": "robot_id"}
POSE_SORT_FIELDS = {"timestamp": "ts_ms", "robotId": "robot_id"}
SortKey = tuple[str, Literal["asc", "desc"]]
CHUNK_IDENTITY: tuple[SortKey, ...] = (
    ("timestamp", "desc"),
    ("row", "asc"),
    ("column", "asc"),
    ("robotId", "asc"),
)
POSE_IDENTITY: tuple[SortKey, ...] = (("timestamp", "desc"), ("robotId", "asc"))

_INT = re.compile(r"[0-9]+")
_TRUE, _FALSE = {"true", "1"}, {"false", "0", ""}


class QueryError(ValueError):
    """A malformed query parameter; the message names it and says what is accepted."""


class ChunkQuery(msgspec.Struct, frozen=True):
    row: int | None = None
    column: int | None = None
    timestamp_ms: int | None = None
    updated_since_ms: int | None = None
    updated_before_ms: int | None = None
    robot_id: str | None = None
    sort: tuple[SortKey, ...] = (("timestamp", "desc"),)
    latest: bool = False
    reduced: bool = False
    type: str = "pgm_base64_compressed"
    limit: int = DEFAULT_LIMIT
    skip: int = 0

    @property
    def order(self) -> tuple[SortKey, ...]:
        """The requested sort plus the identity as tie-breaker (each field once)."""
        return _with_identity(self.sort, CHUNK_IDENTITY)


class PoseQuery(msgspec.Struct, frozen=True):
    robot_id: str | None = None
    timestamp_ms: int | None = None
    updated_since_ms: int | None = None
    updated_before_ms: int | None = None
    sort: tuple[SortKey, ...] = (("timestamp", "desc"),)
    latest: bool = False
    limit: int = DEFAULT_LIMIT
    skip: int = 0

    @property
    def order(self) -> tuple[SortKey, ...]:
        return _with_identity(self.sort, POSE_IDENTITY)


def _with_identity(sort: Sequence[SortKey], identity: Sequence[SortKey]) -> tuple[SortKey, ...]:
    fields = {f for f, _ in sort}
    return tuple(sort) + tuple(k for k in identity if k[0] not in fields)


# --- parsing ---------------------------------------------------------------------------


def parse_time(name: str, value: str) -> int:
    """ISO 8601 (UTC when no zone is given) or epoch milliseconds, 1970 to 2262."""
    ms = parse_query_instant(value)
    if ms is None:
        raise QueryError(
            f"query parameter {name!r}: {value!r} is neither ISO 8601 "
            "(e.g. 2018-12-20T23:34:33, UTC when no zone is given) nor epoch "
            "milliseconds between 1970 and 2262"
        )
    return ms


def _int(name: str, value: str, low: int, high: int) -> int:
    if not _INT.fullmatch(value.strip()):
        raise QueryError(f"query parameter {name!r}: {value!r} is not a whole number >= {low}")
    number = int(value.strip())
    if not low <= number <= high:
        raise QueryError(f"query parameter {name!r}: {number} is outside {low}..{high}")
    return number


def _bool(name: str, value: str) -> bool:
    v = value.strip().lower()
    if v in _TRUE:
        return True
    if v in _FALSE:
        return False
    raise QueryError(f"query parameter {name!r}: {value!r} is not true or false")


def _sort(value: str, fields: Mapping[str, str]) -> tuple[SortKey, ...]:
    keys: list[SortKey] = []
    allowed = ", ".join(f"{f}:asc|desc" for f in fields)
    for part in value.split(","):
        field, _, direction = part.strip().partition(":")
        direction = (direction or "asc").strip().lower()
        if field not in fields or direction not in ("asc", "desc"):
            raise QueryError(
                f"query parameter 'sort': {part.strip()[:80]!r} is not one of {allowed}"
            )
        if field in {f for f, _ in keys}:
            raise QueryError(f"query parameter 'sort': {field!r} appears twice")
        keys.append((field, direction))  # type: ignore[arg-type]
    if len(keys) > MAX_SORT_KEYS:
        raise QueryError(f"query parameter 'sort': at most {MAX_SORT_KEYS} fields")
    return tuple(keys)


def _page(params: Mapping[str, str]) -> tuple[int, int]:
    limit = _int("limit", params["limit"], 0, MAX_LIMIT) if "limit" in params else DEFAULT_LIMIT
    skip = _int("skip", params["skip"], 0, MAX_WINDOW) if "skip" in params else 0
    if skip + limit > MAX_WINDOW:
        raise QueryError(
            f"skip + limit ({skip} + {limit}) is over {MAX_WINDOW}; page further "
            "with updatedBefore/updatedSince instead of skip"
        )
    return limit, skip


def _times(params: Mapping[str, str]) -> dict[str, Any]:
    out = {}
    for name, attr in (
        ("timestamp", "timestamp_ms"),
        ("updatedSince", "updated_since_ms"),
        ("updatedBefore", "updated_before_ms"),
    ):
        if name in params:
            out[attr] = parse_time(name, params[name])
    return out


def _robot_id(params: Mapping[str, str]) -> dict[str, Any]:
    if "robotId" not in params:
        return {}
    robot = params["robotId"]
    if not 1 <= len(robot) <= 64:
        raise QueryError("query parameter 'robotId' must be 1 to 64 characters")
    return {"robot_id": robot}


def parse_chunk_query(params: Mapping[str, str]) -> ChunkQuery:
    """GET /api/chunk-service/chunks parameters (unknown ones are ignored)."""
    fields: dict[str, Any] = {**_times(params), **_robot_id(params)}
    for name in ("row", "column"):
        if name in params:
            fields[name] = _int(name, params[name], 0, 65_535)
    if "sort" in params:
        fields["sort"] = _sort(params["sort"], CHUNK_SORT_FIELDS)
    for name in ("latest", "reduced"):
        if name in params:
            fields[name] = _bool(name, params[name])
    if "type" in params:
        if params["type"] not in CHUNK_TYPES:
            raise QueryError(
                f"query parameter 'type': {params['type'][:40]!r} is not one of "
                f"{', '.join(CHUNK_TYPES)}"
            )
        fields["type"] = params["type"]
    fields["limit"], fields["skip"] = _page(params)
    return ChunkQuery(**fields)


def parse_pose_query(params: Mapping[str, str]) -> PoseQuery:
    """GET /api/coordinate-service/robots parameters (unknown ones are ignored)."""
    fields: dict[str, Any] = {**_times(params), **_robot_id(params)}
    if "sort" in params:
        fields["sort"] = _sort(params["sort"], POSE_SORT_FIELDS)
    if "latest" in params:
        fields["latest"] = _bool("latest", params["latest"])
    fields["limit"], fields["skip"] = _page(params)
    return PoseQuery(**fields)


def latest_instant(query: ChunkQuery | PoseQuery, now_ms: int) -> int:
    """The instant a `latest=true` query reads the map (robots) at: just before
    `updatedBefore` (exclusive, like every `updatedBefore`), else `now_ms`."""
    if query.updated_before_ms is not None:
        return query.updated_before_ms - 1
    return now_ms


# --- the fold (memory store, latest paths) --------------------------------------------

Row = TypeVar("Row")


def matches(row: Any, query: ChunkQuery | PoseQuery) -> bool:
    """Whether a ChunkRow/ChunkState (PoseRow) passes the query's filters."""
    ts = row.ts_ms
    if query.timestamp_ms is not None and ts != query.timestamp_ms:
        return False
    if query.updated_since_ms is not None and ts < query.updated_since_ms:
        return False
    if query.updated_before_ms is not None and ts >= query.updated_before_ms:
        return False
    if query.robot_id is not None and row.robot_id != query.robot_id:
        return False
    if isinstance(query, ChunkQuery):
        if query.row is not None and row.row != query.row:
            return False
        if query.column is not None and row.column != query.column:
            return False
    return True


def _sorted(rows: list[Row], order: Sequence[SortKey], fields: Mapping[str, str]) -> list[Row]:
    # Stable sorts from the last key to the first give the combined order.
    for field, direction in reversed(order):
        attr = fields[field]
        rows.sort(key=attrgetter(attr), reverse=direction == "desc")
    return rows


def select(
    rows: Iterable[Row], query: ChunkQuery | PoseQuery, ignore_time: bool = False
) -> list[Row]:
    """Filter, sort and page rows as the store does (`ignore_time`: the instant was
    applied already, as in a `latest` read where updatedBefore chose the instant)."""
    if ignore_time:
        query = msgspec.structs.replace(query, updated_before_ms=None)
    fields = CHUNK_SORT_FIELDS if isinstance(query, ChunkQuery) else POSE_SORT_FIELDS
    kept = [r for r in rows if matches(r, query)]
    ordered = _sorted(kept, query.order, fields)
    return ordered[query.skip : query.skip + query.limit]


def chunk_id(row: int, column: int, timestamp: str) -> str:
    """The 2019 chunk id: `row:3_column:2_2018-12-20T23:34:33`."""
    return f"row:{row}_column:{column}_{timestamp}"


def pose_id(robot_id: str, timestamp: str) -> str:
    """The 2019 coordinate id: `robotId:blabla_2018-12-20T23:34:33`."""
    return f"robotId:{robot_id}_{timestamp}"


_CHUNK_ID = re.compile(r"row:([0-9]{1,5})_column:([0-9]{1,5})_(.+)")


def parse_chunk_id(text: str) -> tuple[int, int, int]:
    """(row, column, event time ms) of a 2019 chunk id; QueryError if it is not one."""
    m = _CHUNK_ID.fullmatch(text)
    ms = parse_timestamp(m.group(3)) if m else None
    if m is None or ms is None:
        raise QueryError(
            f"{text[:120]!r} is not a chunk id like row:3_column:2_2018-12-20T23:34:33"
        )
    return int(m.group(1)), int(m.group(2)), ms


_COLUMNS = {"timestamp": "ts", "row": "row", "column": "col", "robotId": "robot_id"}


def sort_column(field: str) -> str:
    """The ClickHouse column of a whitelisted sort field (KeyError for anything else)."""
    return _COLUMNS[field]
