"""The 2019 game page: drive a robot and paint the chunk under it through the robots' API
(pose over MQTT-over-WebSocket, chunks over REST or MQTT)."""

from __future__ import annotations

import json
import re
import time

import httpx
import pytest

TIMEOUT_MS = 30_000


def _open(page, stack, robot_id: str) -> None:
    page.goto(f"{stack.api_url}/controller")
    page.locator("header input").fill(robot_id)
    page.wait_for_function(
        "() => document.querySelector('[data-testid=link]')"
        "?.innerText.startsWith('MQTT connected')",
        timeout=TIMEOUT_MS,
    )


def _shown_position(page) -> tuple[float, float]:
    text = page.locator("header").inner_text()
    x, y = re.search(r"x (-?[\d.]+) m · y (-?[\d.]+) m", text).groups()
    return float(x), float(y)


def _painted_chunk(page, stack, robot_id: str) -> tuple[int, int, bytes]:
    """Waits for the page to report a painted chunk, then for the map to hold it by robot_id."""
    page.wait_for_function(
        "() => document.body.innerText.includes('painted chunk')", timeout=TIMEOUT_MS
    )
    text = page.locator("header").inner_text()
    row, column = (int(v) for v in text.split("painted chunk ")[1].split()[0].split(":"))
    deadline = time.monotonic() + 30
    found = None
    while time.monotonic() < deadline and found is None:
        chunks = httpx.get(f"{stack.api_url}/api/v1/map", timeout=30).json()["chunks"]
        found = next(
            (
                c
                for c in chunks
                if (c["row"], c["column"]) == (row, column) and c["robotId"] == robot_id
            ),
            None,
        )
        time.sleep(0.3)
    assert found is not None, "the painted chunk never reached the map"
    raw = httpx.get(
        f"{stack.api_url}/api/v1/chunk-contents/{found['content_hash']}", params={"encoding": "raw"}
    ).content
    return row, column, raw


def _give_token(page, stack) -> None:
    """Pastes the stack's writer token into the page, as an operator does (docs/access.md)."""
    field = page.locator('[data-testid="api-token"]')
    field.fill(stack.api_secrets().writers[0])
    field.dispatch_event("change")


def test_paint_without_a_token_says_what_rest_writes_need(page, history_stack) -> None:
    """Painting via REST without a writer token stores nothing and says where the token is."""
    stack = history_stack
    _open(page, stack, "controller-anonymous")
    page.evaluate("() => localStorage.removeItem('mapservice.apiToken')")
    page.locator('[data-testid="api-token"]').fill("")
    page.locator('[data-testid="api-token"]').dispatch_event("change")
    page.locator('[data-testid="paint-black"]').click()
    page.wait_for_function(
        "() => document.body.innerText.includes('need a writer token')", timeout=TIMEOUT_MS
    )
    assert "writer-token" in page.locator("header").inner_text()


def test_paint_black_reaches_the_map(page, history_stack) -> None:
    """Driving and painting black (REST, with the writer token pasted) stores an all-black chunk under the robot, by its id."""
    stack = history_stack
    _open(page, stack, "controller-1")
    _give_token(page, stack)
    page.locator('[data-testid="right"]').click()
    page.locator('[data-testid="right"]').click()
    page.locator('[data-testid="up"]').click()
    page.locator('[data-testid="paint-black"]').click()
    _, _, raw = _painted_chunk(page, stack, "controller-1")
    assert set(raw) == {0}
    assert not page.errors


def test_paint_white_over_mqtt_reaches_the_map(page, history_stack) -> None:
    """Painting white with 'via MQTT' publishes on the robot's chunk topic (iot/chunks/create/<id>) and the chunk is stored."""
    stack = history_stack
    _open(page, stack, "controller-mqtt")
    page.locator('[data-testid="left"]').click()
    page.locator('[data-testid="paint-via"]').select_option("mqtt")
    page.locator('[data-testid="paint-white"]').click()
    _, _, raw = _painted_chunk(page, stack, "controller-mqtt")
    assert set(raw) == {254}
    assert not page.errors


def test_driving_moves_the_stored_pose(page, history_stack) -> None:
    """Arrow buttons move the robot (where the floor is free), and its pose (MQTT
    iot/coordinates/{id}) is stored there."""
    stack = history_stack
    robot = "controller-drive"
    _open(page, stack, robot)
    # Each press moves 0.5 m, or the robot stays and says why (a rack or the map's edge).
    x, y = _shown_position(page)
    steps = {"right": (0.5, 0.0), "left": (-0.5, 0.0), "up": (0.0, 0.5), "down": (0.0, -0.5)}
    moved = 0
    for button in ("right", "right", "right", "up", "up", "left", "down"):
        page.locator(f'[data-testid="{button}"]').click()
        nx, ny = _shown_position(page)
        if page.locator('[data-testid="message"]').inner_text().startswith("stopped:"):
            assert (nx, ny) == (x, y)
        else:
            assert (nx, ny) == (x + steps[button][0], y + steps[button][1])
            moved += 1
        x, y = nx, ny
    assert moved >= 2, "the robot could hardly move from its start"
    deadline = time.monotonic() + 30
    stored = None
    while time.monotonic() < deadline:
        robots = httpx.get(f"{stack.api_url}/api/v1/robots", timeout=30).json()["robots"]
        stored = next((r for r in robots if r["robotId"] == robot), None)
        if stored and stored["position"][:2] == [x, y]:
            break
        time.sleep(0.3)
    assert stored is not None, "the controller's robot never appeared in /api/v1/robots"
    assert stored["position"][:2] == [x, y]
    assert stored["online"]
    legacy = httpx.get(
        f"{stack.api_url}/api/coordinate-service/robots",
        params={"robotId": robot, "latest": "true"},
        timeout=30,
    ).json()
    assert legacy[0]["robotId"] == robot
    assert legacy[0]["pose"]["position"] == {"x": x, "y": y, "z": 0}
    # Standing still, the page keeps reporting once a second, like a robot.
    later = stored
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and later["ts_ms"] <= stored["ts_ms"]:
        time.sleep(0.5)
        robots = httpx.get(f"{stack.api_url}/api/v1/robots", timeout=30).json()["robots"]
        later = next(r for r in robots if r["robotId"] == robot)
    assert later["ts_ms"] > stored["ts_ms"], "no pose after the last move (no 1 Hz heartbeat)"
    assert later["position"][:2] == [x, y]
    assert not page.errors


def test_without_websocket_url_the_page_says_so(page, history_stack) -> None:
    """With no MAPSERVICE_MQTT_WS_URL the page shows that poses are not sent, and how to fix it."""
    stack = history_stack
    page.route(
        "**/api/v1/client-config",
        lambda route: route.fulfill(
            content_type="application/json",
            body=json.dumps(
                {
                    "mqtt_ws_url": None,
                    "coordinate_topic_prefix": "iot/coordinates/",
                    "create_chunk_topic": "iot/chunks/create",
                }
            ),
        ),
    )
    page.goto(f"{stack.api_url}/controller")
    help_text = page.locator('[data-testid="link-help"]')
    help_text.wait_for(timeout=TIMEOUT_MS)
    assert "MAPSERVICE_MQTT_WS_URL" in help_text.inner_text()
    assert page.locator('[data-testid="link"]').inner_text() == "MQTT not configured"
    assert not page.errors


# ---- where the broker checks robot identities (mapservice up --auth, production) ---------


@pytest.fixture(scope="module")
def auth_stack(tmp_path_factory):
    """The service with Mosquitto checking robot identities; controller-auth has a credential."""
    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.local.checkout import TEST_UI_ENV
    from mapservice.local.stack import Stack
    from tests.fixtures.paths import MAPS
    from tests.integration.conftest import run_stack

    stack = Stack(
        tmp_path_factory.mktemp("ui-auth-stack"),
        mqtt="mosquitto",
        mqtt_auth=True,
        extra_env=dict(TEST_UI_ENV),
    )
    try:  # a failed start stops what it had started, not only a finished module
        run_stack(stack, meta_for(load_ros_map(MAPS / "warehouse.yaml")))
        stack.controller_password = stack.add_robot("controller-auth").password  # type: ignore[attr-defined]
        yield stack
    finally:
        stack.stop()


def test_under_robot_identities_the_page_asks_for_the_robots_password(page, auth_stack) -> None:
    """Anonymous, the broker refuses the page and it says to type the robot's MQTT password."""
    page.goto(f"{auth_stack.api_url}/controller")
    page.locator("header input").fill("controller-auth")
    page.locator("header input").dispatch_event("change")
    refused = page.locator('[data-testid="link-refused"]')
    refused.wait_for(timeout=TIMEOUT_MS)
    assert (
        "MQTT password" in refused.inner_text()
        and "robot add controller-auth" in refused.inner_text()
    )


def test_with_the_robots_password_the_page_drives_and_paints_as_that_robot(
    page, auth_stack
) -> None:
    """With controller-auth's password the page connects, its pose is stored and a chunk painted over MQTT lands on its own topic."""
    stack = auth_stack
    page.goto(f"{stack.api_url}/controller")
    page.locator("header input").fill("controller-auth")
    page.locator("header input").dispatch_event("change")
    password = page.locator('[data-testid="mqtt-password"]')
    password.fill(stack.controller_password)
    password.dispatch_event("change")
    page.wait_for_function(
        "() => document.querySelector('[data-testid=link]')"
        "?.innerText.startsWith('MQTT connected')",
        timeout=TIMEOUT_MS,
    )
    page.locator('[data-testid="right"]').click()
    deadline = time.monotonic() + 30
    stored = None
    while time.monotonic() < deadline and stored is None:
        robots = httpx.get(f"{stack.api_url}/api/v1/robots", timeout=30).json()["robots"]
        stored = next((r for r in robots if r["robotId"] == "controller-auth"), None)
        time.sleep(0.3)
    assert stored is not None, "the page's pose never arrived under robot identities"
    page.locator('[data-testid="paint-via"]').select_option("mqtt")
    assert (
        page.locator('[data-testid="paint-via"] option[value=mqtt]').get_attribute("title")
        == "iot/chunks/create/controller-auth"
    )
    page.locator('[data-testid="paint-grey"]').click()
    _, _, raw = _painted_chunk(page, stack, "controller-auth")
    assert set(raw) == {205}
    assert not page.errors


def test_racks_and_the_map_edge_stop_the_robot(page, history_stack) -> None:
    """Driving right across the floor, the robot stops where the map picture has an occupied
    pixel (or at the map's edge) and says so; its stored pose is where it stopped, never
    inside the rack or off the map."""
    import io

    from PIL import Image

    stack = history_stack
    robot = "controller-walls"
    _open(page, stack, robot)
    x0, y0 = _shown_position(page)
    for _ in range(80):  # 40 m: the warehouse is 30 m wide
        page.locator('[data-testid="right"]').click()
        if page.locator('[data-testid="message"]').inner_text().startswith("stopped:"):
            break
    message = page.locator('[data-testid="message"]').inner_text()
    assert message.startswith("stopped:"), f"drove 40 m right from x {x0} m without stopping"
    x, y = _shown_position(page)
    assert y == y0 and x >= x0
    meta = httpx.get(f"{stack.api_url}/api/chunk-service/meta", timeout=30).json()
    res, (ox, oy) = meta["resolution"], meta["origin"][:2]
    picture = Image.open(
        io.BytesIO(httpx.get(f"{stack.api_url}/api/v1/map/png", timeout=30).content)
    ).convert("L")
    if "occupied" in message:
        bx, by = (float(v) for v in re.search(r"x (-?[\d.]+) m, y (-?[\d.]+) m", message).groups())
        col, row = int((bx - ox) / res), int(meta["height"] - (by - oy) / res)
        assert picture.getpixel((col, row)) < 90, "the named pixel is not occupied"
        assert x + 0.25 < bx <= x + 0.5 + 0.25 + res  # within the next step, not yet touched
    else:
        assert message == "stopped: the map's edge"
        assert x + 0.5 + 0.25 > ox + meta["width"] * res
    deadline = time.monotonic() + 30
    stored = None
    while time.monotonic() < deadline:
        stored = next(
            (
                r
                for r in httpx.get(f"{stack.api_url}/api/v1/robots", timeout=30).json()["robots"]
                if r["robotId"] == robot
            ),
            None,
        )
        if stored and stored["position"][:2] == [x, y]:
            break
        time.sleep(0.3)
    assert stored is not None and stored["position"][:2] == [x, y]
    now = int(time.time() * 1000)
    poses = httpx.get(
        f"{stack.api_url}/api/v1/poses",
        params={"from": now - 300_000, "to": now + 1000},
        timeout=30,
    ).json()
    xs = [p["position"][0] for p in poses if p["robotId"] == robot]
    assert xs and max(xs) == x  # no pose was sent past the stop
    from .test_investigator import screenshot

    screenshot(page, "ui-controller-stopped.png")
    assert not page.errors
