"""VDA 5050 facts in the history (schema v12), the same in both stores: poses from states
and visualizations, errors, exact connection instants, the latest factsheet; a vehicle
off the known maps stored without a drawn pose."""

from __future__ import annotations

import math

import pytest

from mapservice.core.events import decode
from mapservice.core.intake import Intake
from mapservice.core.wire2019 import Limits
from mapservice.ingest.router import Router
from mapservice.settings import Settings
from tests.conftest import sparse_snapshots
from tests.fixtures import vda5050 as vda

NOW = 1_795_255_200_000


def events(settings: Settings, messages: list[tuple[str, dict, int]], limits: Limits = Limits()):
    router = Router(settings, "gw")
    out = []
    for subtopic, msg, receive_ms in messages:
        record = router.route(
            f"uagv/v2/{msg['manufacturer']}/{msg['serialNumber']}/{subtopic}",
            vda.encode(msg),
            receive_ms,
            Intake(limits),
        )
        assert record.reason is None, record.value
        out.append(decode(record.value))
    return out


def test_vda_facts_are_stored_and_read_back(store) -> None:
    v, m, s = "2.1.0", "Acme", "001"
    batch = events(
        Settings(vda5050_map_transforms={"hall": (1.0, 2.0, 0.0)}),
        [
            ("connection", vda.connection(v, m, s, NOW - 10_000, "ONLINE"), NOW - 10_000),
            ("factsheet", vda.factsheet(v, m, s, NOW - 9_000), NOW - 9_000),
            (
                "state",
                vda.state(
                    v,
                    m,
                    s,
                    NOW - 8_000,
                    x=3.0,
                    y=4.0,
                    theta=math.pi,
                    battery=55.0,
                    charging=True,
                    loads=[{"loadId": "a"}],
                    errors=(("FATAL", "bumper", "hit"), ("WARNING", "lowBattery", "")),
                ),
                NOW - 8_000,
            ),
            ("visualization", vda.visualization(v, m, s, NOW - 7_000, x=5.0, y=6.0), NOW - 7_000),
            ("state", vda.state(v, m, s, NOW - 6_000, map_id="cellar"), NOW - 6_000),
            # The last will: composed at connect time, offline when the broker sent it.
            ("connection", vda.connection(v, m, s, NOW - 10_000, "CONNECTIONBROKEN"), NOW - 5_000),
        ],
    )
    store.append(batch)
    store.append(batch)  # a redelivery changes nothing
    poses = store.poses(NOW - 60_000, NOW, robot_id="Acme:001")
    # Transformed by the hall's (1, 2) offset; the state on "cellar" is not drawn.
    assert [(p.ts_ms, p.x, p.y) for p in poses] == [
        (NOW - 8_000, 4.0, 6.0),
        (NOW - 7_000, 6.0, 8.0),
    ]
    assert [(p.battery_level, p.charging, p.loaded) for p in poses] == [(55.0, True, True)] * 2
    assert poses[0].qz == 1.0  # theta pi about z
    assert poses[0].path == ((4.0, 6.0),)
    facts = store.vda_facts("Acme:001", NOW - 60_000, NOW)
    assert [(e.ts_ms, e.level, e.type, e.description) for e in facts.errors] == [
        (NOW - 8_000, "FATAL", "bumper", "hit"),
        (NOW - 8_000, "WARNING", "lowBattery", ""),
    ]
    assert [(c.ts_ms, c.state, c.sent_ms) for c in facts.connections] == [
        (NOW - 10_000, "ONLINE", NOW - 10_000),
        (NOW - 5_000, "CONNECTIONBROKEN", NOW - 10_000),
    ]
    assert facts.factsheet is not None and facts.factsheet.vda_version == "2.1.0"
    assert '"serialNumber":"001"' in facts.factsheet.factsheet
    assert store.vda_facts("Other:1", NOW - 60_000, NOW).connections == []


# The store contract's kinds but ClickHouse over HTTP: there this test's apply_retention
# took minutes (the served chDB's query, not the client, was busy), beyond a fast test;
# the retention tests of test_store_retention_contract.py do run over HTTP.
@pytest.mark.parametrize("store", ["memory", "clickhouse"], indirect=True)
def test_vda_facts_expire_with_the_retention(store, ev) -> None:
    """Errors and connection states older than the retention's first day are dropped with
    the other day partitions; the latest factsheet stays."""
    old = NOW - 9 * 86_400_000
    v, m, s = "2.0.0", "Acme", "001"
    sparse_snapshots(store)  # tens of snapshots for these days, not a thousand
    store.append(
        events(
            Settings(),
            [
                ("connection", vda.connection(v, m, s, old, "ONLINE"), old),
                ("factsheet", vda.factsheet(v, m, s, old), old),
                ("state", vda.state(v, m, s, old, errors=(("FATAL", "bumper", ""),)), old),
            ],
            Limits(retention_ms=30 * 86_400_000),
        )
    )
    store.append(
        [
            ev.chunk("r1", old, 1, 2, bytes(10_000)),
            ev.chunk("r1", NOW - 3_600_000, 1, 2, bytes(10_000)),
        ]
    )
    store.build_snapshots(NOW - 60_000)
    store.apply_retention(NOW)
    facts = store.vda_facts("Acme:001", old - 1, NOW)
    assert (facts.errors, facts.connections) == ([], [])
    assert facts.factsheet is not None and facts.factsheet.ts_ms == old


def test_the_fleets_facts_and_the_states_that_clear_errors(store) -> None:
    """vda_fleet_facts: every vehicle with facts in the window; a state without errors after
    one with errors ends them (error_clears), a second error-free state does not."""
    v = "2.0.0"
    store.append(
        events(
            Settings(),
            [
                ("state", vda.state(v, "Acme", "001", NOW - 9_000), NOW - 9_000),
                (
                    "state",
                    vda.state(v, "Acme", "001", NOW - 8_000, errors=(("FATAL", "bumper", "hit"),)),
                    NOW - 8_000,
                ),
                (
                    "state",
                    vda.state(v, "Acme", "001", NOW - 7_000, errors=(("FATAL", "bumper", "hit"),)),
                    NOW - 7_000,
                ),
                ("state", vda.state(v, "Acme", "001", NOW - 6_000), NOW - 6_000),
                ("state", vda.state(v, "Acme", "001", NOW - 5_000), NOW - 5_000),
                ("connection", vda.connection(v, "Beta", "7", NOW - 4_000, "ONLINE"), NOW - 4_000),
                ("factsheet", vda.factsheet(v, "Gamma", "9", NOW - 4_000), NOW - 4_000),
            ],
        )
    )
    fleet = store.vda_fleet_facts(NOW - 60_000, NOW)
    assert sorted(fleet) == ["Acme:001", "Beta:7"]  # a factsheet alone is no fact of the window
    acme = fleet["Acme:001"]
    assert [e.ts_ms for e in acme.errors] == [NOW - 8_000, NOW - 7_000]
    assert acme.error_clears == [NOW - 6_000]
    assert [c.state for c in fleet["Beta:7"].connections] == ["ONLINE"]
    assert store.vda_facts("Acme:001", NOW - 60_000, NOW).error_clears == [NOW - 6_000]
    # A window starting at the clear still sees it (the state before counts).
    assert store.vda_fleet_facts(NOW - 6_000, NOW)["Acme:001"].error_clears == [NOW - 6_000]
    assert store.vda_fleet_facts(NOW - 60_000, NOW - 8_500) == {}


def test_each_vehicles_connection_state_at_an_instant(store) -> None:
    """The latest state at or before the instant and after `since`, of the robots asked
    for; of two at one instant ONLINE."""
    v = "2.1.0"
    store.append(
        events(
            Settings(),
            [
                (
                    "connection",
                    vda.connection(v, "Acme", "1", NOW - 10_000, "ONLINE"),
                    NOW - 10_000,
                ),
                ("connection", vda.connection(v, "Acme", "1", NOW - 5_000, "OFFLINE"), NOW - 5_000),
                ("connection", vda.connection(v, "Acme", "2", NOW - 4_000, "OFFLINE"), NOW - 4_000),
                ("connection", vda.connection(v, "Acme", "2", NOW - 4_000, "ONLINE"), NOW - 4_000),
                # the last will: offline when the broker sent it
                (
                    "connection",
                    vda.connection(v, "Acme", "3", NOW - 60_000, "CONNECTIONBROKEN"),
                    NOW - 3_000,
                ),
            ],
        )
    )
    robots = ["Acme:1", "Acme:2", "Acme:3", "Other:9"]

    def at(at_ms: int, since_ms: int = NOW - 3_600_000, asked=robots) -> dict[str, str]:
        return {r: c.state for r, c in store.connection_states_at(at_ms, since_ms, asked).items()}

    assert at(NOW - 5_001) == {"Acme:1": "ONLINE"}
    assert at(NOW - 5_000) == {"Acme:1": "OFFLINE"}
    assert at(NOW) == {"Acme:1": "OFFLINE", "Acme:2": "ONLINE", "Acme:3": "CONNECTIONBROKEN"}
    assert at(NOW, since_ms=NOW - 5_000) == {"Acme:2": "ONLINE", "Acme:3": "CONNECTIONBROKEN"}
    assert at(NOW, asked=["Acme:3"]) == {"Acme:3": "CONNECTIONBROKEN"}
    assert at(NOW, asked=[]) == {}
