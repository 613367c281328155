"""Operators command robots from the replay, in Chromium against the shared stack: with an
operator token the selected robot's details offer Pause, Resume, Cancel goal and Go to a
point of interest standing now; a command is stored with who sent it, shows as sent until
the robot answers, then as its answer (a rejection with the robot's reason), and is marked
on the timeline; an accepted pause shows a "paused" badge. A refusal shows the server's
message (a robot it never heard of). A token without the operator scope gets no command buttons.

The shared stack runs no simulated robot: the robot's answers are published here with
mosquitto_pub on its command-events topic, as a robot would. Where others do not look:
everything happens now, to the loaded history's last robot, at a point of interest in the
map's far corner. The screenshot goes to test-artifacts/ui/ and, with
MAPSERVICE_UPDATE_SCREENSHOTS=1, to docs/ui-commands.png."""

from __future__ import annotations

import time

import httpx

from mapservice.core.wire2019 import format_timestamp
from tests.fixtures.mosquitto import mosquitto_pub

from .test_annotations_ui import give_token, operator_token
from .test_investigator import TIMEOUT_MS, api, open_at, screenshot

ROBOT = "robot-0002"  # the loaded history's last robot (conftest.ROBOTS = 3)
POI_NAME = "ui-cmd dock"


def commands(stack) -> dict[str, dict]:
    now = int(time.time() * 1000)
    got = api(
        stack, "/api/v1/commands", **{"from": now - 600_000, "to": now + 60_000, "robot": ROBOT}
    )
    return {c["commandId"]: c for c in got["commands"]}


def stored_of(stack, command_id: str) -> dict:
    """The command as stored (202 means Kafka has it; the processors store it a moment later)."""
    deadline = time.monotonic() + 60
    while (found := commands(stack).get(command_id)) is None and time.monotonic() < deadline:
        time.sleep(0.3)
    assert found is not None, f"{command_id} was not stored"
    return found


def answer(stack, command_id: str, status: str, reason: str = "") -> None:
    """The robot's ack, as the robot publishes it; waits until it is stored."""
    body = {
        "robotId": ROBOT,
        "commandId": command_id,
        "type": "ack",
        "status": status,
        "reason": reason,
        "timestamp": format_timestamp(int(time.time() * 1000)),
    }
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        # The gateway takes an answer only to a command it delivered: again until it has.
        mosquitto_pub(stack.mqtt_port, f"iot/robots/{ROBOT}/command-events", body)
        for _ in range(6):
            ack = commands(stack)[command_id]["ack"]
            if ack is not None:
                assert (ack["status"], ack["reason"]) == (status, reason)
                return
            time.sleep(0.5)
    raise AssertionError(f"the ack of {command_id} was not stored")


def sent_row(page, before: set[str]) -> str:
    """The id of the command row that appeared after a click (and stays: a read under way
    when the command was sent must not drop it from the list)."""
    page.wait_for_function(
        "(before) => [...document.querySelectorAll('[data-testid=\"command-row\"]')]"
        ".some((r) => !before.includes(r.dataset.id))",
        arg=sorted(before),
        timeout=TIMEOUT_MS,
    )
    (new,) = rows(page) - before
    return new


def rows(page) -> set[str]:
    return set(
        page.eval_on_selector_all(
            '[data-testid="command-row"]', "rs => rs.map((r) => r.dataset.id)"
        )
    )


def state_of(page, cid: str, state: str) -> None:
    page.wait_for_selector(
        f'[data-testid="command-row"][data-id="{cid}"][data-state="{state}"]', timeout=TIMEOUT_MS
    )


def test_an_operator_pauses_sends_and_sees_the_robots_answers(page, history_stack) -> None:
    stack = history_stack
    token = operator_token(stack)
    auth = {"Authorization": f"Bearer {token}"}
    r = httpx.post(
        f"{stack.api_url}/api/v1/annotations",
        headers=auth,
        timeout=30,
        json={"shape": "poi", "name": POI_NAME, "kind": "station", "x": 14.0, "y": 14.0},
    )
    assert r.status_code in (200, 201), r.text
    poi = r.json()
    open_at(page, stack, f"?panels=annotations&sel={ROBOT}")
    page.evaluate("() => localStorage.removeItem('mapservice.apiToken')")
    page.wait_for_selector('[data-testid="command-panel"]', state="attached", timeout=TIMEOUT_MS)
    assert page.locator('[data-testid="command-pause"]').count() == 0
    give_token(page, token)
    page.wait_for_selector('[data-testid="command-pause"]', timeout=TIMEOUT_MS)

    # Pause: stored with who sent it, shown as sent (no robot has answered), marked on the timeline.
    before = rows(page)
    page.click('[data-testid="command-pause"]')
    pause = sent_row(page, before)
    state_of(page, pause, "sent")
    stored = stored_of(stack, pause)
    assert (stored["kind"], stored["robotId"], stored["ack"]) == ("pause", ROBOT, None)
    assert stored["issuedBy"].startswith("operator:")
    assert page.locator('[data-testid="paused-badge"]').count() == 0

    # The robot accepts: the row says so, and at the playhead after it the robot is paused.
    answer(stack, pause, "accepted")
    state_of(page, pause, "accepted")
    page.evaluate(
        "() => window.__replay.seek(Date.now())"
    )  # the span reaches the command: its mark
    mark = page.wait_for_selector(
        f'[data-testid="command-mark"][data-ts="{stored["issued_ms"]}"]', timeout=TIMEOUT_MS
    )
    assert f"pause {ROBOT} by {stored['issuedBy']}: accepted" in (mark.text_content() or "")
    page.wait_for_selector('[data-testid="paused-badge"]', timeout=TIMEOUT_MS)
    page.evaluate("(t) => window.__replay.seek(t)", stored["issued_ms"] - 1000)
    page.wait_for_selector('[data-testid="paused-badge"]', state="detached", timeout=TIMEOUT_MS)

    # Go to the point of interest standing now: stored with its position; the robot refuses, with its reason.
    page.wait_for_selector(
        f'[data-testid="command-poi"] option[value="{poi["id"]}"]',
        state="attached",
        timeout=TIMEOUT_MS,
    )
    page.select_option('[data-testid="command-poi"]', poi["id"])
    before = rows(page)
    page.click('[data-testid="command-goto"]')
    goto = sent_row(page, before)
    stored = stored_of(stack, goto)
    assert (stored["kind"], stored["poiId"], stored["target"]["x"], stored["target"]["y"]) == (
        "goto_poi",
        poi["id"],
        14.0,
        14.0,
    )
    answer(stack, goto, "rejected", "paused: resume first")
    state_of(page, goto, "rejected")
    assert (
        f"go to {POI_NAME} {ROBOT} by {stored['issuedBy']}: rejected (paused: resume first)"
        in page.inner_text(f'[data-testid="command-row"][data-id="{goto}"]')
    )
    page.evaluate("() => window.__replay.seek(Date.now())")  # after the pause: the badge
    page.wait_for_selector('[data-testid="paused-badge"]', timeout=TIMEOUT_MS)
    page.wait_for_timeout(1000)
    screenshot(page, "ui-commands.png")
    r = httpx.delete(f"{stack.api_url}/api/v1/annotations/{poi['id']}", headers=auth, timeout=30)
    assert r.status_code in (200, 204), r.text

    # Resume and Cancel goal reach the store too.
    for kind in ("resume", "cancel"):
        before = rows(page)
        page.click(f'[data-testid="command-{kind}"]')
        assert stored_of(stack, sent_row(page, before))["kind"] == kind

    # The server refuses a command to a robot it never heard of: its message is shown.
    open_at(page, stack, "?panels=annotations&sel=ui-cmd-ghost")  # the token stays in this browser
    page.click('[data-testid="command-pause"]', timeout=TIMEOUT_MS)
    error = page.wait_for_selector('[data-testid="command-error"]', timeout=TIMEOUT_MS).inner_text()
    assert "pause refused: 404" in error and "has reported no pose within the retention" in error
    assert page.locator('[data-testid="command-row"]').count() == 0
    assert page.errors == []


def test_a_token_without_the_operator_scope_gets_no_command_buttons(page, history_stack) -> None:
    stack = history_stack
    writer = stack.api_secrets().writers[0]
    open_at(page, stack, f"?panels=annotations&sel={ROBOT}")
    give_token(page, writer)
    page.wait_for_function("() => localStorage.getItem('mapservice.apiToken') !== null")
    page.wait_for_timeout(1500)  # the scopes are asked for again
    assert page.locator('[data-testid="command-panel"]').count() == 1
    for kind in ("pause", "resume", "cancel", "goto", "poi"):
        assert page.locator(f'[data-testid="command-{kind}"]').count() == 0
    r = httpx.post(
        f"{stack.api_url}/api/v1/commands",
        json={"robotId": ROBOT, "kind": "pause"},
        headers={"Authorization": f"Bearer {writer}"},
        timeout=30,
    )
    assert r.status_code == 403 and "operator" in r.json()["detail"]
    assert page.errors == []
