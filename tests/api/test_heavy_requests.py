"""The heaviest requests a client may send, against the API as `serve` runs it (uvicorn with
its own protocol settings, the access guard, the pools, the analysts' /clickhouse): while
each runs, /healthz and /readyz answer within a second (the kubelet's probes: a slow one
restarts the pod), and the request gets its answer within a stated bound.

- the largest zone an operator may draw (the vertex cap, spanning nearly the rasterising
  cap), GEOS's worst valid outline, and a zone one vertex over the cap;
- an image bomb and a checkerboard as a keep-out mask to import;
- a gzip bomb and a 5,000-field multipart body on /clickhouse;
- the worst statements an analyst may send: one that runs until the time limit and one that
  grows until the memory limit;
- a week's heatmap of the fleet as the largest picture allowed (16 M pixels), and one whose
  picture would be larger.

Each run prints its figures and the machine's load average (`-rP` shows them)."""

from __future__ import annotations

import base64
import gzip

import httpx
import pytest

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.zone_geometry import MAX_ZONE_VERTICES
from mapservice.local.embedded import free_port
from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.http_protocol import MAX_QUERY_BYTES, SqlUser, clickhouse_http_app
from mapservice.sql.read_only import ReadOnlyLimits
from mapservice.sql.request_body import MAX_FORM_FIELDS
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.api.access_kit import OPERATOR_TOKEN as OPERATOR
from tests.api.access_kit import settings_for
from tests.api.test_annotations import NOW
from tests.conftest import meta_event
from tests.geometry_kit import (
    checkerboard,
    largest_allowed_zone_doc,
    mask_png,
    mask_yaml,
    parallel_comb_ring,
    png_bomb,
)
from tests.heavy_requests_kit import probe_during
from tests.mapservice.sql.serving import ServedApi

# Timed probes: in the integration part, which runs one test at a time on the machine.
pytestmark = [pytest.mark.integration, pytest.mark.alone]

ANALYST = ("analyst", "an-analysts-password")
# The analysts' time limit here: the worst statement runs this long, then is stopped.
ANALYST_TIME_LIMIT_S = 3
# Every refusal within this; an allowed zone's checks and storing within ZONE_WITHIN_S.
REFUSAL_WITHIN_S = 5.0
ZONE_WITHIN_S = 10.0
# A map of 80 x 80 chunks of 100 px at 5 cm: 400 m square, 64 M cells (the rasterising cap).
CHUNKS = 80
ORIGIN, RESOLUTION = (-1.5, 2.0), 0.05
# The heatmap's picture: 4,000 x 4,000 cells, the 16 M pixels allowed.
HEATMAP_SIDE_CELLS = 4000
HEATMAP_WITHIN_S = 20.0


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    engine = ChdbEngine(
        tmp_path_factory.mktemp("api-sql") / "ch",
        read_only_settings=ReadOnlyLimits(max_execution_time_s=ANALYST_TIME_LIMIT_S).settings(),
    )
    settings = settings_for("open", api_host="127.0.0.1", api_port=free_port())
    store = MemoryStore()
    store.append([meta_event(NOW - 86_400_000, chunk_rows=CHUNKS, chunk_cols=CHUNKS)])
    store.append(fleet_poses())
    sql = clickhouse_http_app(engine, [SqlUser(*ANALYST, read_only=True)])
    app = create_app(
        settings, store, {}, ManualClock(NOW), publisher=MemoryPublisher(), sql_app=sql
    )
    with ServedApi(app, settings) as served:
        yield served.url
    engine.close()


def fleet_poses() -> list:
    """Six hours of five robots driving loops (a pose a second), and two robots standing
    at opposite corners of a square of HEATMAP_SIDE_CELLS 0.5 m cells: the heatmap's picture
    is that square, one pixel a cell."""
    from tests.conftest import pose_event

    start = NOW - 6 * 3_600_000
    poses = [
        pose_event(f"r{r}", t, 10.0 + 5 * r + (t // 1000 % 600) * 0.1, 20.0 + r)
        for r in range(5)
        for t in range(start, NOW, 1000)
    ]
    far = (HEATMAP_SIDE_CELLS - 1) * 0.5 + 0.25
    return [
        *poses,
        pose_event("corner-a", start, 0.25, 0.25),
        pose_event("corner-b", start, far, far),
    ]


def probed(api: str, label: str, send):
    return probe_during([f"{api}/healthz", f"{api}/readyz"], send, label=label)


def post_zone(api: str, doc: dict) -> httpx.Response:
    return httpx.post(
        f"{api}/api/v1/annotations",
        json=doc,
        headers={"Authorization": f"Bearer {OPERATOR}"},
        timeout=60,
    )


def import_mask(api: str, png: bytes) -> httpx.Response:
    return httpx.post(
        f"{api}/api/v1/annotations/import-mask",
        json={
            "yaml": mask_yaml(RESOLUTION, ORIGIN),
            "image_base64": base64.b64encode(png).decode(),
        },
        headers={"Authorization": f"Bearer {OPERATOR}"},
        timeout=60,
    )


def post_sql(api: str, body: bytes, headers: dict[str, str] | None = None) -> httpx.Response:
    return httpx.post(f"{api}/clickhouse", content=body, auth=ANALYST, headers=headers, timeout=60)


# --- zones --------------------------------------------------------------------------------


def test_the_largest_allowed_zone_is_stored_while_the_probes_answer(api) -> None:
    # 190 m round the map's middle: (2 x 190 / 0.05)² = 57.8 M cells, just under the cap.
    middle = (ORIGIN[0] + CHUNKS * 5 / 2, ORIGIN[1] + CHUNKS * 5 / 2)
    doc = largest_allowed_zone_doc(radius_m=190.0, cx=middle[0], cy=middle[1])
    assert sum(len(r) for r in [doc["polygon"], *doc["holes"]]) == MAX_ZONE_VERTICES
    run = probed(api, "largest allowed zone", lambda: post_zone(api, doc))
    reply = run.assert_responsive(max_heavy_s=ZONE_WITHIN_S)
    assert reply.status_code == 201, reply.text


def test_the_worst_valid_outline_is_stored_while_the_probes_answer(api) -> None:
    doc = {
        "shape": "zone",
        "kind": "keep_out",
        "name": "comb",
        "polygon": parallel_comb_ring(MAX_ZONE_VERTICES),
    }
    run = probed(api, "GEOS's worst valid outline", lambda: post_zone(api, doc))
    reply = run.assert_responsive(max_heavy_s=ZONE_WITHIN_S)
    assert reply.status_code == 201, reply.text


def test_a_zone_over_the_vertex_cap_is_a_422_while_the_probes_answer(api) -> None:
    doc = largest_allowed_zone_doc(radius_m=50.0, cx=100.0, cy=100.0)
    doc["polygon"] = doc["polygon"] + [[100.0 + 50.0, 100.0 - 0.001]]
    run = probed(api, "zone one vertex over the cap", lambda: post_zone(api, doc))
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 422 and str(MAX_ZONE_VERTICES) in reply.text, reply.text


# --- keep-out masks -----------------------------------------------------------------------


def test_an_image_bomb_is_a_422_while_the_probes_answer(api) -> None:
    png = png_bomb(12_000, 14_000)  # 168 M pixels in a few hundred KB
    run = probed(api, f"PNG bomb ({len(png)} bytes)", lambda: import_mask(api, png))
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 422, reply.text


def test_a_checkerboard_mask_is_a_422_while_the_probes_answer(api) -> None:
    png = mask_png(checkerboard(CHUNKS * 100, CHUNKS * 100))
    run = probed(api, f"checkerboard mask ({len(png)} bytes)", lambda: import_mask(api, png))
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 422, reply.text


# --- the analysts' /clickhouse -------------------------------------------------------------


def test_a_gzip_bomb_on_clickhouse_is_a_400_while_the_probes_answer(api) -> None:
    """300 MiB of zeros in 300 KB of gzip (the size that once grew the API by 1.4 GB)."""
    stream = gzip.compress(bytes(1024 * 1024), 9)  # one member per MiB: 300 members
    body = stream * 300
    assert len(body) < MAX_QUERY_BYTES
    run = probed(
        api,
        f"gzip bomb on /clickhouse ({len(body)} bytes, 300 MiB decoded)",
        lambda: post_sql(api, body, {"Content-Encoding": "gzip"}),
    )
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 400, reply.text
    assert f"more than {MAX_QUERY_BYTES} bytes" in reply.text


def test_five_thousand_fields_on_clickhouse_are_a_400_while_the_probes_answer(api) -> None:
    body = b"".join(
        b'--zz\r\nContent-Disposition: form-data; name="param_p%d"\r\n\r\n1\r\n' % n
        for n in range(5000)
    )
    body += b'--zz\r\nContent-Disposition: form-data; name="query"\r\n\r\nSELECT 1\r\n--zz--\r\n'
    run = probed(
        api,
        "5,000-field multipart on /clickhouse",
        lambda: post_sql(api, body, {"Content-Type": "multipart/form-data; boundary=zz"}),
    )
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 400, reply.text
    assert f"more than {MAX_FORM_FIELDS} fields" in reply.text


@pytest.mark.parametrize(
    ("statement", "stopped_by"),
    [
        # Hashes a number at a time for ever: stopped by the time limit (408, as a
        # ClickHouse server answers TIMEOUT_EXCEEDED).
        (
            "SELECT count() FROM numbers(1000000000000) WHERE NOT ignore(sipHash64(number))",
            {"TIMEOUT_EXCEEDED": 408},
        ),
        # Collects every number into one array: stopped by the memory limit (500, as a
        # server answers MEMORY_LIMIT_EXCEEDED) or the time limit, whichever the machine's
        # speed meets first.
        (
            "SELECT length(groupArray(number)) FROM numbers(100000000000)",
            {"MEMORY_LIMIT_EXCEEDED": 500, "TIMEOUT_EXCEEDED": 408},
        ),
    ],
    ids=["time", "memory"],
)
def test_the_worst_analyst_statement_is_stopped_while_the_probes_answer(
    api, statement: str, stopped_by: dict[str, int]
) -> None:
    run = probed(
        api,
        f"analyst statement stopped by a limit ({' or '.join(stopped_by)})",
        lambda: post_sql(api, statement.encode()),
    )
    reply = run.assert_responsive(max_heavy_s=ANALYST_TIME_LIMIT_S + REFUSAL_WITHIN_S)
    (limit,) = [name for name in stopped_by if f"({name})" in reply.text] or [reply.text]
    assert reply.status_code == stopped_by[limit], reply.text


# --- heatmaps ------------------------------------------------------------------------------


def get_heatmap(api: str, **params) -> httpx.Response:
    week = {"from": NOW - 7 * 86_400_000 + 120_000, "to": NOW, "kind": "occupancy"}
    return httpx.get(f"{api}/api/v1/heatmap", params={**week, **params}, timeout=60)


def test_the_largest_heatmap_picture_is_drawn_while_the_probes_answer(api) -> None:
    run = probed(api, "a week's heatmap, 16 M pixels", lambda: get_heatmap(api, format="png"))
    reply = run.assert_responsive(max_heavy_s=HEATMAP_WITHIN_S)
    assert reply.status_code == 200, reply.text
    assert reply.content[16:24] == HEATMAP_SIDE_CELLS.to_bytes(4, "big") * 2  # IHDR size


def test_a_heatmap_picture_over_the_cap_is_a_422_while_the_probes_answer(api) -> None:
    run = probed(
        api, "heatmap picture over the cap", lambda: get_heatmap(api, format="png", scale=2)
    )
    reply = run.assert_responsive(max_heavy_s=HEATMAP_WITHIN_S)
    assert reply.status_code == 422 and "pixels" in reply.text, reply.text
