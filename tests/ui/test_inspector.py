"""The conflict inspector and the export button in Chromium, against a running service with
loaded history: a conflict's two writes side by side with their robots and times, a click
that lands just after the later write, a map upload never listed as a conflict, and the
visible span downloaded as MCAP (read back with the mcap reader: battery, charging, loaded
and planned paths) and as CSV. Screenshots go to test-artifacts/ui/ and, with
MAPSERVICE_UPDATE_SCREENSHOTS=1, to docs/."""

from __future__ import annotations

import base64
import csv
import io
import json
import time
import zlib

import httpx
import pytest
from mcap.reader import make_reader
from PIL import Image

from mapservice.api.routers.exports import utc_file_time
from mapservice.core.wire2019 import content_hash, format_timestamp
from tests.fixtures.mosquitto import mosquitto_pub

from .test_investigator import TIMEOUT_MS, api, open_at, screenshot

CONFLICT_ROBOTS = ("insp-a", "insp-b")


def post_chunk(
    stack, robot: str, ts_ms: int, row: int, column: int, value: int, size: tuple[int, int]
) -> str:
    """A chunk write through the 2019 REST API, as a robot (or `mapservice map upload`) sends it."""
    pixels = bytes([value]) * (size[0] * size[1])
    body = {
        "row": row,
        "column": column,
        "robotId": robot,
        "timestamp": format_timestamp(ts_ms),
        "pgmB64compressedData": base64.b64encode(zlib.compress(pixels)).decode(),
    }
    r = httpx.post(
        f"{stack.api_url}/api/chunk-service/chunks",
        json=body,
        timeout=30,
        headers={"Authorization": f"Bearer {stack.api_secrets().writers[0]}"},
    )
    r.raise_for_status()
    return content_hash(pixels).hex()


def test_a_conflicts_two_writes_side_by_side_and_no_upload(page, history_stack) -> None:
    """The map uploader writes a chunk, then two robots write it differently 5 s apart:
    the inspector lists one conflict (the robots'), never the upload's, with both writes'
    pixels, robots and times; a click lands just after the later write with its content on
    the map and the chunk outlined. The conflicts table holds no row naming the upload."""
    stack = history_stack
    meta = httpx.get(f"{stack.api_url}/api/chunk-service/meta", timeout=30).json()
    size = (meta["CHUNK_WIDTH"], meta["CHUNK_HEIGHT"])
    t = stack.history.start_ms + 20 * 60_000
    # A chunk no loaded robot wrote within two conflict windows of the test's writes.
    near = {
        (w["row"], w["column"])
        for w in api(
            stack,
            "/api/v1/chunk-events",
            **{"from": t - 130_000, "to": t + 130_000, "limit": 100_000},
        )
    }
    row, col = next(
        (r, c)
        for r in range(meta["CHUNK_ROWS"] - 1, -1, -1)
        for c in range(meta["CHUNK_COLS"] - 1, -1, -1)
        if (r, c) not in near
    )
    post_chunk(stack, "map-upload", t - 10_000, row, col, 205, size)
    hash_a = post_chunk(stack, CONFLICT_ROBOTS[0], t, row, col, 0, size)
    hash_b = post_chunk(stack, CONFLICT_ROBOTS[1], t + 5_000, row, col, 254, size)
    window = {"from": t - 60_000, "to": t + 60_000}
    deadline = time.monotonic() + 60
    mine: list[dict] = []
    while time.monotonic() < deadline and not any(c["robot_b"] == CONFLICT_ROBOTS[1] for c in mine):
        mine = [
            c
            for c in api(stack, "/api/v1/conflicts", **window)["conflicts"]
            if (c["row"], c["column"]) == (row, col)
        ]
        time.sleep(0.5)
    assert [(c["robot_a"], c["robot_b"], c["ts_a_ms"], c["ts_ms"]) for c in mine] == [
        (CONFLICT_ROBOTS[0], CONFLICT_ROBOTS[1], t, t + 5_000)
    ]
    # What the processors recorded: the robot's write over the upload is no conflict.
    table = httpx.get(
        f"{stack.api_url}/api/v1/exports/tables/chunk-conflicts", params=window, timeout=60
    ).text
    assert "map-upload" not in table and CONFLICT_ROBOTS[1] in table

    open_at(page, stack, f"?t={t + 60_000}&panels=conflicts")
    selector = f'[data-testid="conflict-row"][data-row="{row}"][data-col="{col}"]'
    page.wait_for_selector(selector, timeout=TIMEOUT_MS)
    rows = page.locator(selector)
    assert rows.count() == 1
    item = rows.first
    assert (
        item.get_attribute("data-robot-a"),
        item.get_attribute("data-robot-b"),
    ) == CONFLICT_ROBOTS
    a, b = (
        item.locator('[data-testid="conflict-write-a"]'),
        item.locator('[data-testid="conflict-write-b"]'),
    )
    # Both writes' pixels, loaded (black and white), with who wrote them and when (UTC).
    page.wait_for_function(
        f"() => [...document.querySelectorAll('{selector} img')].length === 2 && "
        f"[...document.querySelectorAll('{selector} img')].every(i => i.complete && i.naturalWidth > 0)",
        timeout=TIMEOUT_MS,
    )
    assert hash_a in a.locator("img").get_attribute("src") and hash_b in b.locator(
        "img"
    ).get_attribute("src")
    assert CONFLICT_ROBOTS[0] in a.inner_text() and format_timestamp(t)[11:19] in a.inner_text()
    assert (
        CONFLICT_ROBOTS[1] in b.inner_text()
        and format_timestamp(t + 5_000)[11:19] in b.inner_text()
    )
    assert "5.0 s apart" in item.inner_text() and f"row {row}, column {col}" in item.inner_text()
    listed = page.evaluate(
        "() => [...document.querySelectorAll('[data-testid=conflict-row]')]"
        ".flatMap(e => [e.dataset.robotA, e.dataset.robotB])"
    )
    assert listed and "map-upload" not in listed
    item.click()
    page.wait_for_function(
        f"() => window.__replay.playhead === {t + 5_001} && window.__replay.complete",
        timeout=TIMEOUT_MS,
    )
    assert (
        page.evaluate("([r, c]) => window.__replay.cell(r, c).content_hash", [row, col]) == hash_b
    )
    ch, cw = size[1], size[0]
    assert page.evaluate("() => window.__replay.outlined()") == [
        [row * ch, col * cw],
        [(row + 1) * ch, (col + 1) * cw],
    ]
    # The picked chunk's orange outline is drawn above the red conflict box on the same
    # chunk (which is drawn again at every seek): the middle of their shared top edge is orange.
    page.wait_for_timeout(500)
    edge = page.evaluate(
        "([r, c]) => window.__replay.screenPointOfPixel(r, c)", [row * ch, col * cw + cw / 2]
    )
    # A strip across the edge: the 2-pixel stroke may fall between whole pixels (a layout a
    # fraction of a pixel off leaves the centre pixel half covered, a pale orange).
    shot = Image.open(
        io.BytesIO(
            page.screenshot(
                clip={"x": round(edge["x"]), "y": round(edge["y"]) - 2, "width": 1, "height": 5}
            )
        )
    ).convert("RGB")
    strip = [shot.getpixel((0, y)) for y in range(shot.height)]
    assert any(r > 200 and 100 < g < 180 and b < 80 for r, g, b in strip), strip
    page.evaluate("() => window.__replay.fitGrid()")
    page.wait_for_function("() => window.__replay.complete", timeout=TIMEOUT_MS)
    screenshot(page, "ui-conflicts.png")
    assert page.errors == []


def read_mcap(data: bytes) -> tuple[dict, list[tuple[str, int, bytes]]]:
    """(topic -> (encoding, schema name, schema encoding, schema data), messages)."""
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    channels = {
        c.topic: (
            c.message_encoding,
            summary.schemas[c.schema_id].name,
            summary.schemas[c.schema_id].encoding,
            summary.schemas[c.schema_id].data,
        )
        for c in summary.channels.values()
    }
    messages = [
        (ch.topic, m.log_time // 1_000_000, m.data)
        for _, ch, m in make_reader(io.BytesIO(data)).iter_messages()
    ]
    return channels, messages


def test_the_visible_span_downloads_as_mcap_and_csv(page, history_stack) -> None:
    """The export button saves the timeline's span: the MCAP read back holds the map, each
    robot's pose, its state (battery in %, charging, loaded: JSON with its JSON schema, equal
    to the stored poses) and its planned path (foxglove.PosesInFrame); the CSV of chunk
    changes holds the span's writes."""
    stack = history_stack
    # After the loaded history's end (it ends ten minutes before the stack started): the
    # other browser tests look at instants before it, where this robot does not exist yet.
    t = stack.history.end_ms + 5 * 60_000
    # A robot reporting a planned path (the loaded history has none), as a 2019 robot does.
    for i, path in enumerate(([(1.0, 2.0), (3.0, 4.0)], [(3.0, 4.0), (5.0, 1.5)])):
        body = {
            "robotId": "insp-path",
            "timestamp": format_timestamp(t - 300_000 + i * 60_000),
            "pose": {
                "position": {"x": 1.0 + i, "y": 2.0, "z": 0},
                "orientation": {"x": 0, "y": 0, "z": 0, "w": 1},
            },
            "status": {"battery": {"battery_level": 0.42, "charging": True}, "loaded": False},
            "plannedPath": [{"x": x, "y": y} for x, y in path],
        }
        mosquitto_pub(stack.mqtt_port, "iot/coordinates/insp-path", body)
    deadline = time.monotonic() + 60
    while (
        time.monotonic() < deadline
        and len(api(stack, "/api/v1/poses", robotId="insp-path", **{"from": t - 600_000, "to": t}))
        < 2
    ):
        time.sleep(0.5)
    open_at(page, stack, f"?t={t}")
    span = page.evaluate(
        "() => { const [f, t] = window.__replay.span(); return [Math.floor(f), Math.ceil(t)]; }"
    )
    assert "UTC" in page.inner_text('[data-testid="export-span"]')
    page.select_option('[data-testid="export-kind"]', "mcap")
    with page.expect_download(timeout=TIMEOUT_MS) as info:
        page.click('[data-testid="export-button"]')
    download = info.value
    assert download.suggested_filename.endswith(".mcap")
    data = open(download.path(), "rb").read()
    page.wait_for_function(
        "() => document.querySelector('[data-testid=export-status]')?.innerText.startsWith('saved')"
    )
    assert download.suggested_filename in page.inner_text('[data-testid="export-status"]')
    screenshot(page, "ui-export.png")
    channels, messages = read_mcap(data)
    # Named by its span in readable UTC (2026-11-28_10-00-00, milliseconds when not whole).
    name = download.suggested_filename
    assert name == f"replay_{utc_file_time(span[0])}_to_{utc_file_time(span[1])}_UTC.mcap", name
    from_ms, to_ms = span
    poses = api(stack, "/api/v1/poses", **{"from": from_ms, "to": to_ms, "limit": 100_000})
    robots = sorted({p["robotId"] for p in poses})
    assert robots and channels["/map"][1] == "foxglove.Grid"
    for rid in robots:
        assert channels[f"/robots/{rid}/pose"][1] == "foxglove.PoseInFrame"
        encoding, _name, schema_encoding, schema = channels[f"/robots/{rid}/state"]
        assert (encoding, schema_encoding) == ("json", "jsonschema")
        assert set(json.loads(schema)["properties"]) == {
            "battery_level",
            "battery_percent",
            "charging",
            "loaded",
        }
        states = [
            (ts, json.loads(d)) for topic, ts, d in messages if topic == f"/robots/{rid}/state"
        ]
        stored = [(p["ts_ms"], p) for p in poses if p["robotId"] == rid]
        assert [ts for ts, _ in states] == [ts for ts, _ in stored]
        for (_, s), (_, p) in zip(states, stored):
            assert (s["battery_level"], s["charging"], s["loaded"]) == (
                p["battery_level"],
                p["charging"],
                p["loaded"],
            )
    # Every robot with a planned path in the span has it as a channel, and no other does
    # (this stack is shared: other modules' robots may drive with paths in the span too).
    with_path = {p["robotId"] for p in poses if p.get("path")}
    assert "insp-path" in with_path
    planned = {
        topic.removeprefix("/robots/").removesuffix("/planned_path")
        for topic in channels
        if topic.startswith("/robots/") and topic.endswith("/planned_path")
    }
    assert planned == with_path
    assert channels["/robots/insp-path/planned_path"][1] == "foxglove.PosesInFrame"
    assert len([m for m in messages if m[0] == "/robots/insp-path/planned_path"]) == 2
    state = next(json.loads(d) for topic, _, d in messages if topic == "/robots/insp-path/state")
    assert state["battery_level"] == pytest.approx(0.42) and state["battery_percent"] == 42.0
    assert (state["charging"], state["loaded"]) == (True, False)

    page.select_option('[data-testid="export-kind"]', "chunk-changes")
    with page.expect_download(timeout=TIMEOUT_MS) as info:
        page.click('[data-testid="export-button"]')
    text = open(info.value.path(), encoding="utf-8").read()
    rows = list(csv.DictReader(io.StringIO(text)))
    writes = api(stack, "/api/v1/chunk-events", **{"from": from_ms, "to": to_ms, "limit": 100_000})
    assert len(rows) == len(writes) and "robot_id" in rows[0]
    assert page.errors == []
