"""GET /api/v1/heatmap: a span's cells of one kind as JSON, a translucent PNG of the cells'
bounding box, or a CSV of every measure; bad kinds, cell sizes, scales and spans refused
with a message before any read, too many cells or pixels after the bounded read."""

from __future__ import annotations

import csv
import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.api.routers.heatmaps import SUMMARY_HEADER
from mapservice.core.heatmap_render import ALPHA, CSV_COLUMNS, RAMP
from mapservice.core.incidents import detect
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

NOW = 1_795_255_200_000
T0 = NOW - 120_000


@pytest.fixture
def store(ev) -> MemoryStore:
    """Two minutes: `a` standing at (0.2, 0.2) for 60 s, then driving +x at 0.5 m/s;
    `b` standing at (3.2, 1.2) the whole time; `c` 0.4 m from `b` driving past (a near miss)."""
    s = MemoryStore()
    events = []
    for k in range(120):
        t = T0 + k * 1000
        events += [
            ev.pose("a", t, 0.2 if k < 60 else 0.2 + (k - 60) * 0.5, 0.2),
            ev.pose("b", t, 3.2, 1.2),
            ev.pose("c", t, -20.0 + k * 0.5, 1.6),
        ]
    s.append(events)
    s.append_incidents(detect(s.poses(0, NOW, limit=10**9), NOW), NOW)
    return s


@pytest.fixture
def client(store) -> TestClient:
    return TestClient(
        create_app(Settings(), store, {}, ManualClock(NOW)), raise_server_exceptions=False
    )


def get(client: TestClient, **params):
    return client.get("/api/v1/heatmap", params={"from": T0, "to": NOW, **params})


def test_occupancy_and_dwell_per_cell(client) -> None:
    body = get(client, kind="occupancy").json()
    assert body["unit"] == "robot-seconds" and body["cell_m"] == 0.5
    cells = {(i, j): v for i, j, v in body["cells"]}
    assert cells[(0, 0)] == 61  # a's 61 s there (k = 0 to 60: its first step starts there)
    assert cells[(6, 2)] == 120  # b, the whole span
    assert body["total"] == 3 * 120 and body["max"] == 120
    dwell = {(i, j): v for i, j, v in get(client, kind="dwell").json()["cells"]}
    # Still from its second sample on (the first has no previous one); b likewise.
    assert dwell[(0, 0)] == 60 and dwell[(6, 2)] == 119
    speed = {(i, j): v for i, j, v in get(client, kind="speed").json()["cells"]}
    assert speed[(6, 2)] == 0.0 and speed[(20, 0)] == pytest.approx(0.5)


def test_coarser_cells_sum_the_finer(client) -> None:
    fine = get(client, kind="occupancy").json()
    coarse = get(client, kind="occupancy", cell=2.0).json()
    assert coarse["cell_m"] == 2.0 and coarse["total"] == fine["total"]
    summed: dict[tuple[int, int], float] = {}
    for i, j, v in fine["cells"]:
        summed[(i // 4, j // 4)] = summed.get((i // 4, j // 4), 0) + v
    assert {(i, j): v for i, j, v in coarse["cells"]} == summed
    box = coarse["box"]
    assert (box["i0"], box["j0"]) == (min(k[0] for k in summed), min(k[1] for k in summed))


def test_incidents_are_counted_where_they_were(client, store) -> None:
    found = store.incidents(T0, NOW)
    assert found  # the near miss of b and c
    body = get(client, kind="incidents").json()
    assert body["unit"] == "incidents" and body["total"] == len(found)
    where = {(int(i.x * 1000) // 500, int(i.y * 1000) // 500) for i in found}
    assert {(i, j) for i, j, _ in body["cells"]} == where


def test_the_png_is_the_cells_box_at_the_scale(client) -> None:
    body = get(client, kind="occupancy", cell=1.0).json()
    box = body["box"]
    reply = get(client, kind="occupancy", cell=1.0, format="png", scale=3)
    assert reply.status_code == 200 and reply.headers["content-type"] == "image/png"
    assert reply.content.startswith(b"\x89PNG\r\n\x1a\n")
    image = Image.open(io.BytesIO(reply.content))
    assert image.mode == "RGBA" and image.size == (box["columns"] * 3, box["rows"] * 3)
    pixels = np.asarray(image)
    # North up: the top row is the highest cell row; the fullest cell is the ramp's top.
    i, j, _ = max(body["cells"], key=lambda c: c[2])
    y = (box["j0"] + box["rows"] - 1 - j) * 3
    x = (i - box["i0"]) * 3
    assert tuple(pixels[y + 1, x + 1]) == (*RAMP[-1].astype(int), ALPHA)
    filled = {(c[0], c[1]) for c in body["cells"]}
    assert int((pixels[:, :, 3] > 0).sum()) == len(filled) * 9  # empty cells transparent


@pytest.mark.parametrize("kind", ["occupancy", "dwell", "speed", "incidents"])
@pytest.mark.parametrize(
    ("cell", "window"),
    [
        (0.5, (T0, NOW)),
        (2.0, (T0 + 30_000, NOW - 10_000)),
        (0.5, (NOW - 86_400_000, NOW - 80_000_000)),  # nothing there: no box
    ],
)
def test_the_png_carries_the_grid_s_summary_so_one_request_draws_it(
    client, kind, cell, window
) -> None:
    """The page asks once: the PNG's header holds everything of the JSON but its cells."""
    params = {"kind": kind, "cell": cell, "from": window[0], "to": window[1]}
    grid = client.get("/api/v1/heatmap", params=params).json()
    reply = client.get("/api/v1/heatmap", params={**params, "format": "png"})
    assert reply.status_code == 200
    summary = json.loads(reply.headers[SUMMARY_HEADER])
    del grid["cells"]
    assert summary == grid
    image = Image.open(io.BytesIO(reply.content))
    box = summary["box"]
    assert image.size == ((box["columns"], box["rows"]) if box else (1, 1))
    for other in ("json", "csv"):
        assert (
            SUMMARY_HEADER
            not in client.get("/api/v1/heatmap", params={**params, "format": other}).headers
        )


def test_the_csv_has_every_measure_of_every_cell(client) -> None:
    reply = get(client, kind="occupancy", format="csv")
    assert reply.status_code == 200 and reply.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(reply.text)))
    assert tuple(rows[0]) == CSV_COLUMNS
    by_cell = {(int(r["i"]), int(r["j"])): r for r in rows}
    b = by_cell[(6, 2)]
    assert (b["x_m"], b["y_m"], b["cell_m"]) == ("3", "1", "0.5")
    assert (b["occupancy_s"], b["dwell_s"], b["mean_speed_m_s"]) == ("120", "119", "0")
    occupancy = {(i, j): v for i, j, v in get(client, kind="occupancy").json()["cells"]}
    assert {k: float(r["occupancy_s"]) for k, r in by_cell.items() if k in occupancy} == occupancy


@pytest.mark.parametrize(
    ("params", "status", "says"),
    [
        ({"kind": "heat"}, 422, "occupancy"),
        ({"kind": "occupancy", "cell": 0.3}, 400, "multiple of 0.5 m"),
        ({"kind": "occupancy", "cell": 0.25}, 400, "multiple of 0.5 m"),
        ({"kind": "occupancy", "cell": 20.5}, 400, "from 0.5 to 20 m"),
        ({"kind": "occupancy", "cell": 0}, 400, "multiple of 0.5 m"),
        ({"kind": "occupancy", "cell": "nan"}, 400, "multiple of 0.5 m"),
        ({"kind": "occupancy", "cell": "inf"}, 400, "multiple of 0.5 m"),
        ({"kind": "occupancy", "cell": -1}, 400, "multiple of 0.5 m"),
        ({"kind": "occupancy", "cell": 1.7e308}, 400, "multiple of 0.5 m"),
        ({"kind": "occupancy", "format": "gif"}, 422, "png"),
        ({"kind": "occupancy", "format": "png", "scale": 0}, 400, "between 1 and 16"),
        ({"kind": "occupancy", "format": "png", "scale": 17}, 400, "between 1 and 16"),
        ({"kind": "occupancy", "from": NOW - 8 * 86_400_000}, 400, "longer than"),
        ({"kind": "occupancy", "from": NOW, "to": T0}, 400, "swap them"),
    ],
)
def test_bad_requests_say_why(client, params, status, says) -> None:
    reply = get(client, **params)
    assert reply.status_code == status, reply.text
    assert says in reply.text


@pytest.mark.parametrize(("cell", "ok"), [(0.5, True), (1.5, True), (20.0, True), (0.75, False)])
def test_cell_sizes_are_the_multiples_of_the_finest(client, cell, ok) -> None:
    assert (get(client, kind="dwell", cell=cell).status_code == 200) is ok


def test_too_many_cells_or_pixels_are_refused(client, monkeypatch) -> None:
    from mapservice.api.routers import heatmaps

    monkeypatch.setattr(heatmaps, "MAX_CELLS", 3)
    reply = get(client, kind="occupancy")
    assert reply.status_code == 422 and "more than 3 cells" in reply.text
    monkeypatch.setattr(heatmaps, "MAX_CELLS", 1_000_000)
    monkeypatch.setattr(heatmaps, "MAX_PNG_PIXELS", 100)
    reply = get(client, kind="occupancy", format="png", scale=16)
    assert reply.status_code == 422 and "pixels" in reply.text
    monkeypatch.setattr(heatmaps, "MAX_PNG_PIXELS", 16_000_000)
    assert get(client, kind="occupancy", format="png", scale=16).status_code == 200


def test_an_empty_span_is_an_empty_grid_and_a_transparent_pixel(client) -> None:
    params = {"from": NOW - 86_400_000, "to": NOW - 80_000_000}
    body = get(client, kind="occupancy", **params).json()
    assert body["cells"] == [] and body["box"] is None and body["max"] == 0
    image = Image.open(io.BytesIO(get(client, kind="dwell", format="png", **params).content))
    assert image.size == (1, 1) and image.getpixel((0, 0))[3] == 0


@pytest.mark.parametrize(
    ("kind", "format", "cells", "counts"),
    [
        ("occupancy", "json", 1, 0),
        ("dwell", "png", 1, 0),
        ("speed", "json", 1, 0),
        ("incidents", "json", 0, 1),
        ("incidents", "png", 0, 1),
        ("occupancy", "csv", 1, 1),
    ],
)
def test_each_read_only_where_it_is_shown(
    client, store, monkeypatch, kind, format, cells, counts
) -> None:
    """A week's incidents with their evidence took seconds to read, and the samples' cells
    are not what an incidents picture shows: occupancy, dwell and speed read the cells
    only, the incidents kind only the incidents' counts per cell (never the incidents
    themselves), the CSV (every measure) both."""
    calls: dict[str, int] = {"heatmap_cells": 0, "incidents_per_cell": 0, "incidents": 0}
    for name in calls:
        read = getattr(store, name)

        def counted(*a, _name=name, _read=read, **k):
            calls[_name] += 1
            return _read(*a, **k)

        monkeypatch.setattr(store, name, counted)
    assert get(client, kind=kind, format=format).status_code == 200
    assert calls == {"heatmap_cells": cells, "incidents_per_cell": counts, "incidents": 0}
