"""Operators' commands to VDA 5050 vehicles: the relay sends pause, resume and cancel as
`instantActions` valid against the official schema of the vehicle's version, on the
vehicle's own topic (goto_poi is not sent); the vehicle's `actionStates` naming a command
become its ack and outcome, once each."""

from __future__ import annotations

import pytest

from mapservice.core.commands import CommandAcknowledged, CommandFinished, CommandIssued
from mapservice.core.vda_ids import robot_id_for
from mapservice.ingest.vda5050 import validator
from mapservice.ingest.vda_commands import VdaCommandRefused, VdaCommands, instant_actions_message
from tests.fixtures import vda5050 as vda
from tests.ingest import gateway_kit
from tests.ingest.gateway_kit import NOW

VEHICLE = robot_id_for("acme", "agv 7")  # a space: escaped in the id, plain on the topic


class Gateway(gateway_kit.Gateway):
    def state(self, version: str, action_states: list[dict], serial: str = "agv 7"):
        """The vehicle's state message (VDA 5050 `version`) with these action states."""
        msg = vda.state(version, "acme", serial, NOW + 50)
        msg["instantActionStates" if version.startswith("3") else "actionStates"] = action_states
        return self.ingestor.handle(
            f"uagv/v{version[0]}/acme/{serial}/state", vda.encode(msg), lambda: None
        )


@pytest.fixture
def gw() -> Gateway:
    return Gateway()


def action_state(cid: str, status: str, **extra) -> dict:
    return {"actionId": cid, "actionType": "startPause", "actionStatus": status, **extra}


@pytest.mark.parametrize("version", ["2.0.0", "2.1.0", "3.0.0"])
@pytest.mark.parametrize("kind", ["pause", "resume", "cancel"])
def test_instant_actions_are_valid_against_the_official_schema(version, kind) -> None:
    command = CommandIssued("c-1", VEHICLE, kind, "op", NOW)
    msg = instant_actions_message(command, "acme", "agv 7", version, 3, vda.iso(NOW))
    errors = [e.message for e in validator(version, "instantActions").iter_errors(msg)]
    assert errors == []
    actions = msg["instantActions" if version == "2.0.0" else "actions"]
    assert actions == [
        {
            "actionId": "c-1",
            "actionType": {"pause": "startPause", "resume": "stopPause", "cancel": "cancelOrder"}[
                kind
            ],
            "blockingType": "NONE" if version == "3.0.0" else "HARD",
        }
    ]


def test_the_schemas_check_what_the_versions_name_differently() -> None:
    """The validators are no formality: 2.1's field name fails 2.0's check and the reverse,
    and a missing header fails both."""
    command = CommandIssued("c-1", VEHICLE, "pause", "op", NOW)
    v20 = instant_actions_message(command, "acme", "agv 7", "2.0.0", 3, vda.iso(NOW))
    v21 = instant_actions_message(command, "acme", "agv 7", "2.1.0", 3, vda.iso(NOW))
    assert list(validator("2.0.0", "instantActions").iter_errors(v21))
    assert list(validator("2.1.0", "instantActions").iter_errors(v20))
    for version, msg in (("2.0.0", v20), ("2.1.0", v21)):
        assert list(
            validator(version, "instantActions").iter_errors(
                {k: v for k, v in msg.items() if k != "headerId"}
            )
        )


def test_the_relay_sends_a_vehicle_instant_actions_in_its_version(gw) -> None:
    assert gw.issue("c-1", VEHICLE, "pause")  # not heard from yet: 2.0.0
    gw.state("2.1.0", [])  # now it speaks 2.1
    assert gw.issue("c-2", VEHICLE, "resume")
    (t1, m1), (t2, m2) = gw.sent
    assert t1 == "uagv/v2/acme/agv 7/instantActions" == t2
    assert m1["version"] == "2.0.0" and m1["instantActions"][0]["actionType"] == "startPause"
    assert m2["version"] == "2.1.0" and m2["actions"][0] == {
        "actionId": "c-2",
        "actionType": "stopPause",
        "blockingType": "HARD",
    }
    assert (m1["manufacturer"], m1["serialNumber"]) == ("acme", "agv 7")
    assert m2["headerId"] > m1["headerId"]
    assert m1["timestamp"] == "2026-11-21T10:00:00.000Z"  # RFC 3339, as vehicles demand
    assert not list(validator("2.1.0", "instantActions").iter_errors(m2))
    assert not any(t.startswith("iot/robots/") for t, _ in gw.sent)


def test_goto_poi_is_not_sent_to_a_vehicle_and_2019_robots_are_unchanged(gw) -> None:
    assert not gw.issue("c-1", VEHICLE, "goto_poi")
    assert gw.sent == []
    with pytest.raises(VdaCommandRefused, match="order"):
        gw.ingestor.router.vda_commands.delivery(
            CommandIssued("c-1", VEHICLE, "goto_poi", "op", NOW, "p1", 1.0, 2.0), NOW
        )
    assert gw.issue("c-2", "agv-1", "pause")
    assert gw.sent[0][0] == "iot/robots/agv-1/commands"


def test_action_states_become_the_commands_ack_and_outcome_once(gw) -> None:
    gw.issue("c-1", VEHICLE, "pause")
    gw.issue("c-2", VEHICLE, "cancel")
    gw.state("2.0.0", [action_state("c-1", "WAITING"), action_state("order-action", "RUNNING")])
    assert gw.command_events() == []  # nothing yet; an order's action is no command
    gw.state("2.0.0", [action_state("c-1", "RUNNING")])
    gw.state("2.0.0", [action_state("c-1", "RUNNING")])  # again: no second ack
    gw.state(
        "2.0.0",
        [
            action_state("c-1", "FINISHED"),
            action_state("c-2", "FAILED", resultDescription="no order to cancel"),
        ],
    )
    gw.state("2.0.0", [action_state("c-1", "FINISHED"), action_state("c-2", "FAILED")])
    assert gw.command_events() == [
        CommandAcknowledged("c-1", VEHICLE, "accepted"),
        CommandFinished("c-1", VEHICLE, "done"),
        CommandFinished("c-2", VEHICLE, "failed", "no order to cancel"),
    ]


def test_a_finished_action_acks_and_finishes_at_once_in_3_0(gw) -> None:
    gw.issue("c-1", VEHICLE, "pause")
    record = gw.state("3.0.0", [action_state("c-1", "FINISHED")])
    assert record.reason is None
    assert gw.command_events() == [
        CommandAcknowledged("c-1", VEHICLE, "accepted"),
        CommandFinished("c-1", VEHICLE, "done"),
    ]
    assert gw.sent[0][1]["version"] == "2.0.0"  # sent before the vehicle said 3.0
    gw.issue("c-2", VEHICLE, "resume")
    assert gw.sent[1][0] == "uagv/v3/acme/agv 7/instantActions"
    assert not list(validator("3.0.0", "instantActions").iter_errors(gw.sent[1][1]))


def test_another_vehicle_cannot_answer_a_command(gw) -> None:
    gw.issue("c-1", VEHICLE, "pause")
    gw.state("2.0.0", [action_state("c-1", "FINISHED")], serial="agv 8")
    assert gw.command_events() == []


def test_header_ids_keep_increasing_per_vehicle_across_a_restart() -> None:
    wall = [1_795_255_200.0]
    commands = VdaCommands("uagv", lambda cid: VEHICLE, lambda: wall[0])
    ids = [
        commands.delivery(CommandIssued(f"c-{i}", VEHICLE, "pause", "op", NOW), NOW)[1]["headerId"]
        for i in range(3)
    ]
    restarted = VdaCommands("uagv", lambda cid: VEHICLE, lambda: wall[0] + 5)
    after = restarted.delivery(CommandIssued("c-9", VEHICLE, "pause", "op", NOW), NOW)[1]
    assert ids == sorted(set(ids)) and after["headerId"] > ids[-1]


def test_an_answer_whose_delivery_failed_is_produced_again(gw) -> None:
    """A command event made from a state is retried like the state's own record."""
    gw.issue("c-1", VEHICLE, "pause")
    gw.publisher.fail_with = RuntimeError("kafka away")
    gw.state("2.0.0", [action_state("c-1", "RUNNING")])
    assert gw.command_events() == [] and gw.ingestor.retries_waiting == 2
    gw.publisher.fail_with = None
    gw.ingestor.monotonic = lambda: 1e12  # every retry is due
    assert gw.ingestor.retry_due() == 2
    assert gw.command_events() == [CommandAcknowledged("c-1", VEHICLE, "accepted")]
