"""`mapservice bench foxglove`'s arithmetic (no brokers): the live figures from the clients'
report and the CPU snapshots, a seek's first complete frame from what arrived, and the
command's flags (each says what it does). The whole command runs in
tests/integration/test_bench_foxglove.py."""

from __future__ import annotations

import argparse

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapservice.bench.foxglove import _one_seek, add_parser, live_figures, summary


def snapshots(api_cpu_s: float, wall_s: float) -> tuple[dict, dict]:
    """CpuMeter's snapshots, before and after: the API spent `api_cpu_s`, the gateway 0.5 s."""
    machine = dict.fromkeys(
        ("_bench_process", "_poller_thread", "_loadgen_workers", "_machine_irq")
        + ("_machine_processes", "_machine_steal"),
        0.0,
    )
    before = {"api": 10.0, "gateway": 1.0, **machine, "_wall": 100.0}
    after = {"api": 10.0 + api_cpu_s, "gateway": 1.5, **machine, "_wall": 100.0 + wall_s}
    return before, after


def report(*clients: dict, seconds: float = 10.0) -> dict:
    return {"seconds": seconds, "clients": list(clients)}


def client(messages: int, pose_log_ms: list[int], latencies: list[int], closed=None) -> dict:
    return {
        "messages": messages,
        "bytes": 100 * messages,
        "poses": len(pose_log_ms),
        "latencies": latencies,
        "pose_log_ms": pose_log_ms,
        "closed": closed,
    }


WINDOW = (1_000, 1_999)  # the poses published in it count in the delivered share
PUBLISHED = list(range(1_000, 2_000))


def test_cpu_per_message_is_the_api_process_cpu_over_every_client_message() -> None:
    """2 s of the API's CPU over 20,000 messages (two clients) is 100 µs a message; with
    10 % of a core spent with no client, 1 s of the 2 s is the clients': 50 µs marginal.
    The delivered share counts only the poses published in the window, on both sides (one
    before it, and those after it that were still on their way, count for neither)."""
    before, after = snapshots(api_cpu_s=2.0, wall_s=10.0)
    doc = {"no_clients_api_cpu_percent": 10.0}
    second = [*range(1_000, 1_900), 2_000, 2_001]
    got = live_figures(
        report(client(12_000, [999, *PUBLISHED], [100] * 1001), client(8_000, second, [300])),
        before,
        after,
        node_cpu_s=1.0,
        published_ts=[999, *PUBLISHED, 2_000, 2_001, 2_002],
        window=WINDOW,
        doc=doc,
    )
    assert got["poses_published_in_window"] == 1000
    assert got["messages_received"] == 20_000
    assert got["api_cpu_us_per_message"] == pytest.approx(100.0)
    assert got["marginal_cpu_us_per_message"] == pytest.approx(50.0)
    assert got["api_cpu_percent"] == pytest.approx(20.0)
    assert got["messages_per_s_per_client"] == [1200.0, 800.0]
    assert got["messages_per_s_per_client_median"] == 1000.0
    assert got["poses_received_fraction_min"] == 0.9
    assert got["node_clients_cpu_percent"] == 10.0
    assert got["cpu_percent_of_one_core"]["gateway"] == pytest.approx(5.0)
    assert got["clients_closed"] == []


def test_without_a_baseline_no_marginal_figure_and_a_dropped_client_is_named() -> None:
    before, after = snapshots(api_cpu_s=1.0, wall_s=10.0)
    got = live_figures(
        report(client(10, [1_500], [5]), client(0, [], [], closed="1008 too many")),
        before,
        after,
        0.0,
        [1_500, 1_600],
        WINDOW,
        {},
    )
    assert "marginal_cpu_us_per_message" not in got
    assert got["clients_closed"] == ["1008 too many"]
    assert got["poses_received_fraction_min"] == 0.0


@given(st.lists(st.integers(0, 5_000), min_size=1, max_size=200))
def test_latency_percentiles_are_samples_in_order(latencies: list[int]) -> None:
    before, after = snapshots(1.0, 10.0)
    half = len(latencies) // 2
    got = live_figures(
        report(client(1, [], latencies[:half]), client(1, [], latencies[half:])),
        before,
        after,
        0.0,
        [],
        WINDOW,
        {},
    )
    assert got["pose_latency_samples"] == len(latencies)
    assert got["pose_latency_p50_ms"] in latencies
    assert (
        min(latencies)
        <= got["pose_latency_p50_ms"]
        <= got["pose_latency_p95_ms"]
        <= got["pose_latency_p99_ms"]
        <= got["pose_latency_max_ms"]
        == max(latencies)
    )


class SeekClient:
    """Answers a seek with what the node client would report for it."""

    def __init__(self, grid_ms: float, poses: dict[str, float]) -> None:
        self.grid_ms, self.poses = grid_ms, poses
        self.sent: list[dict] = []

    def send(self, **command) -> int:
        self.sent.append(command)
        return 0

    def wait_for(self, matches, timeout_s, after=0) -> dict:
        event = {
            "event": "seek",
            "at_ms": self.sent[-1]["at_ms"],
            "answer_ms": 2.0,
            "grid_ms": self.grid_ms,
            "poses": self.poses,
        }
        assert matches(event)
        return event


class RobotsApi:
    def __init__(self, standing: list[str]) -> None:
        self.standing = standing
        self.asked: list[dict] = []

    def get(self, path: str, params: dict):
        import httpx

        self.asked.append({"path": path, **params})
        return httpx.Response(
            200,
            json={"robots": [{"robotId": r} for r in self.standing]},
            request=httpx.Request("GET", "http://api" + path),
        )


@pytest.fixture(autouse=True)
def no_gap(monkeypatch):
    monkeypatch.setattr("mapservice.bench.foxglove.SEEK_GAP_S", 0.0)


def test_a_frame_is_complete_when_the_floor_and_every_standing_robot_arrived() -> None:
    """The last of the floor and the standing robots' poses; a pose of a robot that does not
    stand at T (a late subscription's resend) neither completes nor delays the frame."""
    client = SeekClient(grid_ms=40.0, poses={"a": 55.5, "b": 90.25, "gone": 400.0})
    api = RobotsApi(["a", "b"])
    got = _one_seek(client, api, 1_000)
    assert client.sent == [{"op": "seek", "at_ms": 1_000}]
    assert api.asked == [{"path": "/api/v1/robots", "at": 1_000}]
    assert got == {
        "at_ms": 1_000,
        "robots": 2,
        "missing": 0,
        "missing_robots": [],
        "answer_ms": 2.0,
        "grid_ms": 40.0,
        "frame_ms": 90.2,
    }


def test_a_floor_later_than_every_pose_ends_the_frame_and_missing_robots_are_counted() -> None:
    assert _one_seek(SeekClient(120.0, {"a": 10.0}), RobotsApi(["a"]), 5)["frame_ms"] == 120.0
    got = _one_seek(SeekClient(10.0, {"a": 20.0}), RobotsApi(["a", "b", "c"]), 5)
    assert (got["robots"], got["missing"], got["missing_robots"]) == (3, 2, ["b", "c"])


def test_the_summary_quotes_both_phases_and_every_flag_says_what_it_does() -> None:
    doc = summary(
        {
            "live": {"api_cpu_us_per_message": 80.0, "pose_latency_p95_ms": 300},
            "seek": {"frame_p95_ms": 200.0, "load_s": 12.0, "reused": True},
        }
    )
    assert doc["api_cpu_us_per_message"] == 80.0 and doc["pose_latency_p95_ms"] == 300
    assert doc["seek_frame_p95_ms"] == 200.0 and doc["seek_reused"] is True
    assert summary({}) == {}
    kinds = argparse.ArgumentParser().add_subparsers()
    add_parser(kinds)
    parser = kinds.choices["foxglove"]
    flags = [a for a in parser._actions if a.option_strings and a.dest != "help"]
    assert len(flags) >= 12 and all(a.help for a in flags), [a.dest for a in flags if not a.help]
    args = parser.parse_args([])
    assert (args.robots, args.clients, args.seeks, args.seek_robots, args.days) == (
        200,
        10,
        30,
        200,
        7.0,
    )
