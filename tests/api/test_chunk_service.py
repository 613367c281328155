"""The 2019 chunk service (appendix A.1), its reads and deletes: GET /chunks with every
parameter (listing 12), a chunk by id and as PNG, DELETE; over a SpyStore. The writes are
in test_chunk_service_writes.py."""

from __future__ import annotations

import base64
import io
import zlib

import numpy as np
import pytest
from PIL import Image
from structlog.testing import capture_logs

from mapservice.core.legacy_query import MAX_LIMIT
from tests.api.chunk_service_kit import (
    BASE,
    CLOCK_MS,
    NOW,
    TOKEN,
    WRITES,
    anonymous,
    get,
    keys,
    newest_first,
    pixels,
)

# isort: split
from tests.api.chunk_service_kit import client, publisher, settings, store  # noqa: F401  (fixtures)

# --- GET /chunks (listing 12): every parameter --------------------------------------------------


def test_listing_12_fields_and_types(client) -> None:
    """Each chunk has row, column, timestamp, chunk (base64 zlib pixels), type, id and robotId."""
    [first] = get(client, limit=1)
    assert first == {
        "row": 0,
        "column": 0,
        "timestamp": "2026-11-21T10:00:12",
        "chunk": first["chunk"],
        "type": "pgm_base64_compressed",
        "id": "row:0_column:0_2026-11-21T10:00:12",
        "robotId": "r1",
    }
    assert zlib.decompress(base64.b64decode(first["chunk"])) == pixels(12)


def test_defaults_are_ten_newest_first(client) -> None:
    """No parameters: limit 10, sorted timestamp:desc (ties by row, column, robot)."""
    assert keys(get(client)) == newest_first(WRITES)[:10]


def test_limit_and_skip(client) -> None:
    """limit cuts, skip pages on from there."""
    assert keys(get(client, limit=3)) == newest_first(WRITES)[:3]
    assert keys(get(client, limit=3, skip=2)) == newest_first(WRITES)[2:5]
    assert keys(get(client, limit=MAX_LIMIT)) == newest_first(WRITES)


@pytest.mark.parametrize(
    "param, value, expected",
    [
        ("row", "1", lambda w: w[2] == 1),
        ("column", "0", lambda w: w[3] == 0),
        ("robotId", "r1", lambda w: w[0] == "r1"),
        ("timestamp", "2026-11-21T10:00:12", lambda w: w[1] == 12_000),
        ("timestamp", str(NOW + 12_000), lambda w: w[1] == 12_000),
        ("updatedSince", "2026-11-21T10:00:11", lambda w: w[1] >= 11_000),
        ("updatedBefore", "2026-11-21T10:00:02Z", lambda w: w[1] < 2_000),
        ("updatedBefore", "2026-11-21T11:00:02+01:00", lambda w: w[1] < 2_000),
    ],
)
def test_filters(client, param, value, expected) -> None:
    """Each filter selects exactly its writes (since inclusive, before exclusive, no zone = UTC)."""
    assert keys(get(client, limit=100, **{param: value})) == newest_first(
        [w for w in WRITES if expected(w)]
    )


@pytest.mark.parametrize(
    "sort, order",
    [
        ("timestamp:asc", lambda w: (w[1], w[2], w[3], w[0])),
        ("timestamp:desc", lambda w: (-w[1], w[2], w[3], w[0])),
        ("row:asc", lambda w: (w[2], -w[1], w[3], w[0])),
        ("column:desc,robotId:asc", lambda w: (-w[3], w[0], -w[1], w[2])),
    ],
)
def test_sort(client, sort, order) -> None:
    """sort orders by the whitelisted fields, the identity breaking ties."""
    assert keys(get(client, limit=100, sort=sort)) == sorted(WRITES, key=order)


def test_latest_is_each_cells_winner(client, store) -> None:
    """latest=true: one write per chunk, the newest; at one instant the greatest robot id."""
    body = keys(get(client, latest="true", limit=100))
    assert len(body) == 12
    assert ("r2", 12_000, 0, 0) in body and ("r1", 12_000, 0, 0) not in body
    assert ("r0", 0, 0, 0) not in body
    assert store.called("map_at") == [CLOCK_MS + 300_000]  # now plus the allowed clock skew


def test_latest_with_updated_before_is_the_map_at_t_from_map_at(client, store) -> None:
    """latest=true&updatedBefore=T is the whole map just before T, served by map_at (no scan)."""
    body = keys(get(client, latest="true", updatedBefore="2026-11-21T10:00:05", limit=100))
    assert body == newest_first(WRITES[:5])
    assert store.called("map_at") == [NOW + 4_999]
    assert store.called("list_chunks") == []


def test_latest_then_filters_select_among_winners(client) -> None:
    """With latest, row/robotId filter the winners (cell (0,0) is r2's now, so r0 has none there)."""
    assert keys(get(client, latest="true", row="0", robotId="r0", limit=100)) == []
    assert keys(get(client, latest="true", row="0", limit=100)) == newest_first(
        [w for w in WRITES if w[2] == 0 and w[1] != 0 and w[:2] != ("r1", 12_000)]
    )


def test_reduced_leaves_out_chunk_and_type(client) -> None:
    """reduced=true omits `chunk` and `type`; the rest stays."""
    [c] = get(client, limit=1, reduced="true")
    assert set(c) == {"row", "column", "timestamp", "id", "robotId"}
    assert set(get(client, limit=1, reduced="false")[0]) >= {"chunk", "type"}


def test_type_png_returns_base64_png(client) -> None:
    """type=png puts a base64 PNG of the chunk's pixels in `chunk`."""
    [c] = get(client, limit=1, type="png")
    assert c["type"] == "png"
    image = np.asarray(Image.open(io.BytesIO(base64.b64decode(c["chunk"]))))
    assert image.shape == (100, 100) and image.tobytes() == pixels(12)


@pytest.mark.parametrize(
    "params, fragment",
    [
        ({"row": "abc"}, "'row'"),
        ({"column": "-1"}, "'column'"),
        ({"limit": str(MAX_LIMIT + 1)}, "'limit'"),
        ({"limit": "ten"}, "'limit'"),
        ({"skip": "9995", "limit": "10"}, "skip + limit"),
        ({"sort": "timestamp; DROP TABLE chunk_events"}, "'sort'"),
        ({"sort": "chunk:asc"}, "'sort'"),
        ({"sort": "row:sideways"}, "'sort'"),
        ({"latest": "maybe"}, "'latest'"),
        ({"reduced": "yes please"}, "'reduced'"),
        ({"type": "gif"}, "'type'"),
        ({"timestamp": "yesterday"}, "'timestamp'"),
        ({"updatedSince": "2026-13-01"}, "'updatedSince'"),
        ({"updatedBefore": "soon"}, "'updatedBefore'"),
    ],
)
def test_malformed_parameters_are_400(client, params, fragment) -> None:
    """A malformed value is a 400 naming the parameter and what it accepts."""
    r = client.get(f"{BASE}/chunks", params=params)
    assert r.status_code == 400 and fragment in r.json()["detail"], r.text


def test_unknown_parameters_are_ignored(client) -> None:
    """Parameters the 2019 document does not know are ignored, as the 2019 service did."""
    assert get(client, foo="bar", limit=2, page="7") == get(client, limit=2)


# --- GET /chunks/id/{id} and /png ---------------------------------------------------------------


def test_get_by_id_picks_the_winner_of_a_shared_instant(client) -> None:
    """An id names (row, column, time); two robots at that instant: the greatest robot id."""
    r = client.get(f"{BASE}/chunks/id/row:0_column:0_2026-11-21T10:00:12")
    assert r.status_code == 200 and r.json()["robotId"] == "r2"
    assert zlib.decompress(base64.b64decode(r.json()["chunk"])) == pixels(13)


@pytest.mark.parametrize(
    "chunk_id",
    ["row:0_column:0_2026-11-21T10:00:13", "nonsense", "row:x_column:0_2026-11-21T10:00:12"],
)
def test_unknown_or_malformed_id_is_404(client, chunk_id) -> None:
    """An id that names no stored chunk (or no chunk at all) is a 404 with a message."""
    for suffix in ("", "/png"):
        r = client.get(f"{BASE}/chunks/id/{chunk_id}{suffix}")
        assert r.status_code == 404 and "no chunk" in r.json()["detail"]


def test_png_by_id(client) -> None:
    """/chunks/id/{id}/png is the chunk as a greyscale PNG."""
    r = client.get(f"{BASE}/chunks/id/row:2_column:2_2026-11-21T10:00:02/png")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert np.asarray(Image.open(io.BytesIO(r.content))).tobytes() == pixels(2)


# --- DELETE (administrative) ------------------------------------------------------------------


@pytest.mark.parametrize("path", ["chunks", "meta"])
def test_delete_needs_the_admin_token(client, store, path) -> None:
    """DELETE without a token or with a wrong one is 401, with a robot's (writer) token 403; nothing is deleted."""
    assert anonymous(client).delete(f"{BASE}/{path}").status_code == 401
    r = client.delete(f"{BASE}/{path}", headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401
    r = client.delete(f"{BASE}/{path}")
    assert r.status_code == 403 and "MAPSERVICE_ADMIN_TOKEN" in r.json()["detail"]
    assert store.counts().chunk_events == len(WRITES) and store.latest_meta() is not None


def test_delete_chunks_with_token_empties_and_logs(client, store) -> None:
    """DELETE /chunks with the admin token removes every chunk write and logs who did it."""
    with capture_logs() as logs:
        r = client.delete(f"{BASE}/chunks", headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200 and r.json() == {"acknowledged": True, "deleted": len(WRITES)}
    assert get(client) == [] and get(client, latest="true") == []
    assert any(e["event"] == "chunk history deleted by administrator" for e in logs)


def test_delete_meta_with_token(client, store) -> None:
    """DELETE /meta with the admin token removes the meta: GET /meta is then a 404."""
    r = client.delete(f"{BASE}/meta", headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200 and r.json()["deleted"] == 1
    assert client.get(f"{BASE}/meta").status_code == 404
