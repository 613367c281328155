"""`mapservice sim`'s one fleet runner, shared by the simulated robots and the 2019 load
test: a fleet that cannot be made ends the command with why, SIGTERM and Ctrl-C stop it,
an unreachable broker ends with what to do; and its progress logs' pacing."""

from __future__ import annotations

import signal

import pytest

from mapservice.robot import sim_cli


class Fleet:
    def __init__(self, fail_with: BaseException | None = None) -> None:
        self.fail_with = fail_with
        self.stopped = 0
        self.ran = 0

    def run(self) -> None:
        self.ran += 1
        if self.fail_with is not None:
            raise self.fail_with

    def stop(self) -> None:
        self.stopped += 1


@pytest.fixture(autouse=True)
def sigterm_restored():
    before = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, before)


def test_the_runner_runs_the_fleet_it_made_and_sigterm_stops_it() -> None:
    fleet = Fleet()
    assert sim_cli._run_fleet(lambda: fleet, Fleet.run, "mqtt://x:1") is fleet
    assert fleet.ran == 1 and fleet.stopped == 0
    signal.getsignal(signal.SIGTERM)(signal.SIGTERM, None)
    assert fleet.stopped == 1


def test_a_fleet_that_cannot_be_made_ends_the_command_with_why() -> None:
    def bad() -> Fleet:
        raise ValueError("--robots must be at least 1")

    with pytest.raises(SystemExit, match="mapservice sim: --robots must be at least 1"):
        sim_cli._run_fleet(bad, Fleet.run, "mqtt://x:1")


def test_ctrl_c_stops_the_fleet_and_an_unreachable_broker_says_what_to_do() -> None:
    fleet = Fleet(KeyboardInterrupt())
    sim_cli._run_fleet(lambda: fleet, Fleet.run, "mqtt://x:1")
    assert fleet.stopped == 1
    with pytest.raises(SystemExit, match=r"cannot reach the MQTT broker at mqtt://x:1.*--mqtt-url"):
        sim_cli._run_fleet(lambda: Fleet(ConnectionRefusedError()), Fleet.run, "mqtt://x:1")


def test_progress_is_due_at_once_then_once_an_interval(monkeypatch) -> None:
    now = [1000.0]
    monkeypatch.setattr(sim_cli.time, "monotonic", lambda: now[0])
    due = sim_cli._every(10)
    assert due() is True and due() is False
    now[0] += 9.9
    assert due() is False
    now[0] += 0.1
    assert due() is True and due() is False
