"""The 2019 query-string model: defaults, the sort whitelist, bounds, times, ids."""

from __future__ import annotations

import pytest

from mapservice.core.legacy_query import (
    MAX_LIMIT,
    ChunkQuery,
    PoseQuery,
    QueryError,
    chunk_id,
    latest_instant,
    parse_chunk_id,
    parse_chunk_query,
    parse_pose_query,
    pose_id,
)

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z


def test_defaults_are_the_documents() -> None:
    """No parameters: timestamp:desc, latest and reduced false, pgm type, limit 10, skip 0."""
    q = parse_chunk_query({})
    assert q == ChunkQuery()
    assert (q.sort, q.latest, q.reduced, q.type, q.limit, q.skip) == (
        (("timestamp", "desc"),),
        False,
        False,
        "pgm_base64_compressed",
        10,
        0,
    )
    assert parse_pose_query({}) == PoseQuery(sort=(("timestamp", "desc"),), limit=10, skip=0)


def test_query_is_frozen() -> None:
    """A parsed query cannot be changed afterwards."""
    with pytest.raises(AttributeError):
        parse_chunk_query({}).limit = 5  # type: ignore[misc]


@pytest.mark.parametrize(
    "text", ["2026-11-21T10:00:00", "2026-11-21T10:00:00Z", "2026-11-21T11:00:00+01:00", str(NOW)]
)
def test_times_without_zone_are_utc(text) -> None:
    """Zoneless ISO, Z, an offset and epoch ms name the same instant."""
    assert parse_chunk_query({"updatedSince": text}).updated_since_ms == NOW


def test_sort_parses_a_whitelisted_list_and_appends_the_identity() -> None:
    """sort=row:asc,robotId:desc is kept; the identity breaks ties; direction defaults to asc."""
    q = parse_chunk_query({"sort": "row:asc, robotId:DESC"})
    assert q.sort == (("row", "asc"), ("robotId", "desc"))
    assert q.order == (
        ("row", "asc"),
        ("robotId", "desc"),
        ("timestamp", "desc"),
        ("column", "asc"),
    )
    assert parse_pose_query({"sort": "robotId"}).sort == (("robotId", "asc"),)


@pytest.mark.parametrize(
    "sort",
    ["ts:desc", "row:asc", "timestamp:up", "robotId:asc,robotId:desc", "timestamp:desc) --", ""],
)
def test_pose_sort_outside_the_whitelist_is_an_error(sort) -> None:
    """Anything but timestamp/robotId with asc/desc, each once, is refused with the choices."""
    with pytest.raises(QueryError, match="'sort'"):
        parse_pose_query({"sort": sort})


@pytest.mark.parametrize(
    "params", [{"limit": str(MAX_LIMIT + 1)}, {"limit": "-1"}, {"skip": "1.5"}, {"skip": "9991"}]
)
def test_page_bounds(params) -> None:
    """limit <= 10000, whole numbers only, and skip + limit <= 10000."""
    with pytest.raises(QueryError):
        parse_chunk_query(params)


def test_page_at_the_bounds_is_fine() -> None:
    """limit 10000 and skip 9990 with the default limit are the largest accepted."""
    assert parse_chunk_query({"limit": str(MAX_LIMIT)}).limit == MAX_LIMIT
    assert parse_chunk_query({"skip": "9990"}).skip == 9990


@pytest.mark.parametrize(
    "value, expected",
    [("true", True), ("TRUE", True), ("1", True), ("false", False), ("0", False), ("", False)],
)
def test_booleans(value, expected) -> None:
    """latest/reduced accept true/false (any case) and 1/0."""
    assert parse_chunk_query({"latest": value, "reduced": value}).latest is expected


def test_unknown_parameters_are_ignored() -> None:
    """Parameters the document does not name change nothing."""
    assert parse_chunk_query({"colour": "red", "page": "x"}) == ChunkQuery()


def test_latest_instant_is_just_before_updated_before() -> None:
    """latest reads the state just before updatedBefore (exclusive), else now."""
    assert latest_instant(parse_chunk_query({"updatedBefore": str(NOW)}), 5) == NOW - 1
    assert latest_instant(parse_pose_query({}), 5) == 5


def test_ids_round_trip() -> None:
    """The 2019 ids: row:3_column:2_<ts> (parsed back to row, column, ms) and robotId:<id>_<ts>."""
    assert chunk_id(3, 2, "2018-12-20T23:34:33") == "row:3_column:2_2018-12-20T23:34:33"
    assert parse_chunk_id("row:3_column:2_2026-11-21T10:00:00") == (3, 2, NOW)
    assert parse_chunk_id("row:3_column:2_2026-11-21T10:00:00.250Z") == (3, 2, NOW + 250)
    assert pose_id("blabla", "2018-12-20T23:34:33") == "robotId:blabla_2018-12-20T23:34:33"
    for bad in ("row:3_column:2", "row:-1_column:2_2026-11-21T10:00:00", "id"):
        with pytest.raises(QueryError):
            parse_chunk_id(bad)
