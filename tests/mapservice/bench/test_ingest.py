"""Unit tests of the ingest benchmark's latency arithmetic (no brokers)."""

import json

import pytest

from mapservice.bench.ingest.latency import INF, _latencies, _stage_latencies, queryable_times
from mapservice.bench.ingest.probes import LiveListener

KEY = ("pose", "r1", 1_700_000_000_000)


def test_sub_millisecond_hop_to_the_gateway_is_never_negative() -> None:
    """The gateway stamps floored milliseconds; a publish 0.4 ms before it, in the same
    millisecond, counts as 0 s to the gateway, not as a negative time."""
    published = 1_700_000_000.1236  # 0.6 ms into millisecond ...123
    stages = _stage_latencies(
        {KEY: 1_700_000_000_123 / 1000}, {KEY: published + 0.25}, {KEY: published}
    )
    assert stages["publish_to_gateway_p50_s"] == 0.0
    assert abs(stages["gateway_to_queryable_p50_s"] - 0.2506) < 1e-6


def test_stages_split_the_time_at_the_gateway_receive_stamp() -> None:
    """Publish -> gateway plus gateway -> queryable adds up to publish -> queryable."""
    stages = _stage_latencies({KEY: 1000.120}, {KEY: 1001.5}, {KEY: 1000.0})
    total = stages["publish_to_gateway_p50_s"] + stages["gateway_to_queryable_p50_s"]
    assert abs(stages["publish_to_gateway_p50_s"] - 0.120) < 1e-6
    assert abs(total - 1.5) < 1e-6


def test_an_event_is_queryable_at_the_earlier_of_its_push_and_its_first_poll() -> None:
    """The push wins when it came first, the poll when it did, and a pushed-only event counts."""
    other, pushed_only = ("chunk", "r2", 5), ("pose", "r3", 7)
    at = queryable_times({KEY: 10.0, other: 20.0}, {KEY: 9.5, other: 20.5, pushed_only: 30.0})
    assert at == {KEY: 9.5, other: 20.0, pushed_only: 30.0}


def test_the_live_listener_notes_each_event_of_a_batched_frame_and_of_a_single_message() -> None:
    """It asks for batched frames; each event of an array counts, as does a lone object
    (a server from before batching); the first send of an event is the one kept."""
    listener = LiveListener("http://127.0.0.1:8000")
    assert listener.ws_url == "ws://127.0.0.1:8000/api/v1/live?batch=true"
    pose = {"type": "pose", "robotId": "r1", "ts_ms": 1_000, "sent_ms": 1_500}
    chunk = {"type": "chunk", "robotId": "r1", "ts_ms": 2_000, "sent_ms": 2_500}
    listener.note(json.dumps([pose, chunk]))
    listener.note(json.dumps({**pose, "sent_ms": 9_000}))
    assert listener.pushed_at == {("pose", "r1", 1_000): 1.5, ("chunk", "r1", 2_000): 2.5}
    assert listener.messages == 3


def test_latency_bounds_and_unseen_events_count_as_infinite() -> None:
    """Upper bound from the queryable time, lower bound from the last poll that missed it
    (never above the upper one); an event never seen is infinite in both."""
    unseen = ("pose", "r9", 1)
    upper, lower = _latencies({KEY: 10.4}, {KEY: 10.6}, {KEY: 10.0, unseen: 10.0})
    assert [round(v, 6) for v in upper[:1]] == [0.4] and upper[1] == INF
    assert [round(v, 6) for v in lower[:1]] == [0.4] and lower[1] == INF


def test_storage_is_judged_only_on_runs_long_enough() -> None:
    """A 20 s run's storage per robot-day is not judged (no red MISSED for fixed overhead);
    a 2-minute run is, against the 1.5 MB target."""
    from mapservice.bench.ingest.report import storage_verdict

    assert storage_verdict(20, 9e6) is None
    assert storage_verdict(120, 1.4e6) is True
    assert storage_verdict(120, 9e6) is False


def _fleet_figures(**overrides) -> dict:
    figures = {
        "lost": 0,
        "duplicated": 0,
        "sustained_events_per_s": 6000.0,
        "loadgen_schedule_percent": 99.9,
        "latency_pushed_p99_s": 0.8,
        "latency_polled_p99_s": 1.9,
        "latency_p99_s": 0.8,
    }
    return {**figures, **overrides}


def test_live_bounds_hold_and_each_one_can_miss() -> None:
    """5,000 robots within every bound hold; each bound alone, missed, is named."""
    from mapservice.bench.ingest.report import live_bounds

    assert all(ok for *_, ok in live_bounds(5000, _fleet_figures()))
    for key, bad in (
        ("lost", 1),
        ("duplicated", 2),
        ("sustained_events_per_s", 5900.0),
        ("loadgen_schedule_percent", 99.4),
        ("latency_pushed_p99_s", 1.01),
        ("latency_polled_p99_s", 2.2),
        ("latency_pushed_p99_s", None),
    ):
        missed = [
            name for name, _, _, ok in live_bounds(5000, _fleet_figures(**{key: bad})) if not ok
        ]
        assert len(missed) == 1, (key, missed)


def test_a_small_fleet_is_held_to_the_tighter_p99() -> None:
    """Up to 1,000 robots, 99 % of events must be stored within 0.3 s of their publish, by
    the server's own timing (a client's push-or-poll figure is an upper bound, reported);
    above, only push and poll bounds."""
    from mapservice.bench.ingest.report import live_bounds

    def missed(robots: int, **figures) -> list[str]:
        small = _fleet_figures(sustained_events_per_s=1200.0, latency_p99_s=0.35, **figures)
        return [n for n, _, _, ok in live_bounds(robots, small) if not ok]

    assert missed(1000, stored_within_small_fleet_bound=0.995) == []
    assert missed(1000, stored_within_small_fleet_bound=0.985) == ["p99 publish -> stored (server)"]
    assert missed(1000) == ["p99 publish -> stored (server)"]  # no server timing: not held
    assert missed(1001, stored_within_small_fleet_bound=0.5) == []


def test_publish_to_stored_is_read_from_the_servers_histogram_between_two_scrapes() -> None:
    """The bench reads the history consumer's own per-event histogram: the events observed
    between two scrapes, their share within 0.3 s exactly (a bucket bound) and p50/p99
    interpolated within their buckets."""
    from prometheus_client import CollectorRegistry, Histogram, generate_latest

    from mapservice.bench.ingest.metrics import histogram_buckets, stored_latency
    from mapservice.processors.history_consumer import STORED_LATENCY_BUCKETS

    registry = CollectorRegistry()
    hist = Histogram(
        "mapservice_event_to_stored_seconds",
        "test",
        ["topic"],
        buckets=STORED_LATENCY_BUCKETS,
        registry=registry,
    )
    for _ in range(50):
        hist.labels("warm-up").observe(9.0)  # before the run: not counted
    before = histogram_buckets(generate_latest(registry).decode())
    for _ in range(985):
        hist.labels("poses").observe(0.09)
    for _ in range(10):
        hist.labels("states").observe(0.29)
    for _ in range(5):
        hist.labels("poses").observe(0.45)
    stored = stored_latency(before, histogram_buckets(generate_latest(registry).decode()), 0.3)
    assert stored["events"] == 1000
    assert stored["within_bound_fraction"] == pytest.approx(0.995)
    assert 0.075 < stored["p50_s"] <= 0.1
    assert 0.275 < stored["p99_s"] <= 0.3
    for _ in range(20):
        hist.labels("poses").observe(0.45)  # now 2.4 % over 0.3 s: p99 beyond the bound
    late = stored_latency(before, histogram_buckets(generate_latest(registry).decode()), 0.3)
    assert late["within_bound_fraction"] < 0.99 and 0.4 < late["p99_s"] <= 0.5


def test_a_quantile_beyond_the_last_bucket_is_at_least_its_bound() -> None:
    from mapservice.bench.ingest.metrics import bucket_quantile

    assert bucket_quantile({0.1: 0.0, 3600.0: 0.0, float("inf"): 4.0}, 0.99) == 3600.0
    assert bucket_quantile({0.1: 0.0, float("inf"): 0.0}, 0.99) is None


def test_the_ceiling_is_the_last_step_of_an_unbroken_run_that_held() -> None:
    """Steps 1,000 and 2,000 held, 3,000 missed: the ceiling is 2,000; none held: None."""
    from mapservice.bench.ingest.command import ceiling_verdict

    steps = [
        {"robots": 1000, "held": True},
        {"robots": 2000, "held": True},
        {"robots": 3000, "held": False},
    ]
    assert ceiling_verdict(steps) == 2000
    assert ceiling_verdict([{"robots": 1000, "held": False}]) is None


def printed_results(
    capsys, robots: int, seconds: float, latency_clients: bool = True, **figures
) -> str:
    """What print_results prints for one run of `robots` robots over `seconds` with these figures."""
    import argparse

    from rich.console import Console

    from mapservice.bench.ingest.report import print_results

    med = {
        **_fleet_figures(**figures),
        "offered_events_per_s": robots * 1.2,
        "published_events_per_s": robots * 1.2,
        "stats_poses_minus_expected": 0,
        "stats_chunk_events_minus_expected": 0,
        "dead_letters": 0,
        "latency_censored": 0,
        "published_events": int(robots * 1.2 * seconds),
        "bytes_per_robot_day": 2e6,
        "storage.bytes_per_robot_day_events_only": 1e6,
    }
    args = argparse.Namespace(
        robots=robots,
        seconds=seconds,
        mqtt="mosquitto",
        poll_interval=0.1,
        latency_clients=latency_clients,
    )
    facts = {
        "nproc": 2,
        "cpu_model": "x",
        "ram_bytes": 2**30,
        "python": "3",
        "tansu": "t",
        "mosquitto": "m",
    }
    print_results(Console(width=200), args, facts, [med], med)
    return capsys.readouterr().out


def test_a_short_run_is_reported_not_judged(capsys) -> None:
    """A 10 s run prints "not judged" and says it is not representative, never MISSED."""
    out = printed_results(capsys, 5000, 10.0, lost=3, latency_pushed_p99_s=5.0)
    assert "MISSED" not in out and "not judged" in out and "not representative" in out


def test_the_results_show_publish_to_stored_beside_the_clients_figure(capsys) -> None:
    """The judged server timing and the client's push-or-poll upper bound, side by side."""
    out = printed_results(
        capsys,
        1000,
        60.0,
        stored_latency_p50_s=0.101,
        stored_latency_p99_s=0.262,
        stored_within_small_fleet_bound=0.9931,
        received_to_stored_p50_s=0.087,
        received_to_stored_p99_s=0.231,
        latency_p99_s=0.318,
    )
    line = next(line for line in out.splitlines() if "publish -> stored p50 / p99" in line)
    assert "0.101 s / 0.262 s" in line and "ok" in line
    part = next(line for line in out.splitlines() if "gateway received -> stored" in line)
    assert "0.087 s / 0.231 s" in part
    assert "99.31 %" in next(line for line in out.splitlines() if "stored within 0.3 s" in line)
    assert "0.318 s" in next(line for line in out.splitlines() if "p99 (push or poll)" in line)


def test_the_results_show_the_yardstick_measured_before_the_run(capsys) -> None:
    """A run's yardstick appears in the result table, so two runs' machines can be compared."""
    out = printed_results(capsys, 1000, 60.0, yardstick_ms=18.25)
    assert "18.2" in next(line for line in out.splitlines() if "machine yardstick" in line)


def test_a_backlog_still_being_stored_is_waited_for_not_counted_lost() -> None:
    from mapservice.bench.ingest.probes import DrainWatch

    watch = DrainWatch({"poses": 100, "chunk_events": 10}, stall_s=20, max_s=600)
    for t in range(0, 100, 5):  # the store keeps counting, slowly, for 100 s
        watch.observe(t, {"poses": t, "chunk_events": 0})
        assert not watch.given_up(t)
    watch.observe(100, {"poses": 100, "chunk_events": 10})
    assert watch.drained_s == 100 and not watch.given_up(110) and watch.given_up(121)


def test_the_drain_gives_up_once_the_store_stops_counting_or_at_its_cap() -> None:
    from mapservice.bench.ingest.probes import DrainWatch

    stalled = DrainWatch({"poses": 100}, stall_s=20, max_s=600)
    stalled.observe(0, {"poses": 50})
    stalled.observe(10, {"poses": 60})
    assert not stalled.given_up(29) and stalled.given_up(30) and stalled.drained_s is None
    capped = DrainWatch({"poses": 10**9}, stall_s=20, max_s=60)
    for t in range(0, 61, 5):
        capped.observe(t, {"poses": t})
    assert capped.given_up(60) and not capped.given_up(59)


def test_a_loss_is_placed_before_or_after_the_gateways() -> None:
    """Fewer messages confirmed than published: the broker; all of them: after the gateways."""
    from mapservice.bench.ingest.report import loss_side

    assert "broker did not pass them on" in loss_side(-23)
    assert "lost after them" in loss_side(0)


def test_gateway_acks_sum_each_gateways_accepted_and_rejected(monkeypatch) -> None:
    """Each gateway's count is its accepted plus rejected messages from its /metrics."""
    import httpx

    from mapservice.bench.ingest import metrics

    text = (
        "# TYPE mapservice_gateway_messages_total counter\n"
        'mapservice_gateway_messages_total{outcome="accepted"} 100.0\n'
        'mapservice_gateway_messages_total{outcome="rejected"} 2.0\n'
        "# TYPE mapservice_gateway_messages_created gauge\n"
        'mapservice_gateway_messages_created{outcome="accepted"} 1.7e9\n'
    )
    monkeypatch.setattr(metrics.httpx, "get", lambda url, timeout: httpx.Response(200, text=text))
    assert metrics.gateway_acks([1, 2]) == [102.0, 102.0]


def test_history_offset_gaps_reads_reread_and_accepted_from_the_servers_metrics(
    monkeypatch,
) -> None:
    """The guard's gap counts come from the server's /metrics, per outcome, 0 when absent."""
    import httpx

    from mapservice.bench.ingest import metrics

    text = (
        "# TYPE mapservice_consumer_offset_gaps_total counter\n"
        'mapservice_consumer_offset_gaps_total{outcome="reread"} 3.0\n'
        "# TYPE mapservice_consumer_offset_gaps_created gauge\n"
        'mapservice_consumer_offset_gaps_created{outcome="reread"} 1.7e9\n'
    )
    asked = []
    monkeypatch.setattr(
        metrics.httpx,
        "get",
        lambda url, timeout: asked.append(url) or httpx.Response(200, text=text),
    )
    assert metrics.history_offset_gaps(metrics.server_metrics("http://127.0.0.1:9")) == {
        "reread": 3.0,
        "accepted": 0.0,
    }
    assert asked == ["http://127.0.0.1:9/metrics"]


def test_counter_by_label_sums_one_counters_samples_per_label_value() -> None:
    """Only the named counter's _total samples count, summed per value of the label."""
    from mapservice.bench.ingest.metrics import counter_by_label

    text = (
        "# TYPE a_total counter\n"
        'a_total{outcome="x",topic="p"} 1.0\n'
        'a_total{outcome="x",topic="c"} 2.0\n'
        'a_total{outcome="y",topic="c"} 4.0\n'
        "# TYPE b_total counter\n"
        'b_total{outcome="x"} 100.0\n'
    )
    assert counter_by_label(text, "a", "outcome") == {"x": 3.0, "y": 4.0}


def test_store_stages_are_the_histograms_growth_between_two_scrapes() -> None:
    """Per stage: calls and mean ms from the histograms' count and sum deltas; absent ones are 0 calls."""
    from mapservice.bench.ingest.metrics import histogram_totals, store_stages

    def scrape(inserts: int, insert_s: float, batches: int, events: int) -> str:
        return (
            "# TYPE mapservice_sink_insert_seconds histogram\n"
            f'mapservice_sink_insert_seconds_bucket{{le="+Inf"}} {inserts}\n'
            f"mapservice_sink_insert_seconds_count {inserts}\n"
            f"mapservice_sink_insert_seconds_sum {insert_s}\n"
            "# TYPE mapservice_sink_batch_events histogram\n"
            f'mapservice_sink_batch_events_bucket{{le="+Inf"}} {batches}\n'
            f"mapservice_sink_batch_events_count {batches}\n"
            f"mapservice_sink_batch_events_sum {events}\n"
        )

    stages = store_stages(
        histogram_totals(scrape(10, 1.0, 10, 100)),
        histogram_totals(scrape(30, 3.0, 30, 700)),
        wall_s=4.0,
    )
    assert stages["insert"] == {"calls": 20, "mean_ms": 100.0, "busy_percent": 50.0}
    assert stages["conflicts_check"] == {"calls": 0, "mean_ms": None, "busy_percent": 0.0}
    assert (stages["batches"], stages["events_per_batch"]) == (20, 30.0)


class _RecordedWaits:
    """Stands in for the poller's halt event: records each wait and halts after `cycles`."""

    def __init__(self, cycles: int) -> None:
        self.waits: list[float] = []
        self.cycles = cycles

    def is_set(self) -> bool:
        return len(self.waits) >= self.cycles

    def wait(self, seconds: float) -> bool:
        self.waits.append(seconds)
        return self.is_set()


def _slow_poller(monkeypatch, rows: int):
    """A poller whose every read takes 30 ms and returns `rows` rows, at a 10 ms cadence."""
    import time as time_module

    from mapservice.bench.ingest import probes

    poller = probes.QueryablePoller("http://unused", [], interval_s=0.01)
    poller._halt = _RecordedWaits(cycles=3)

    def slow_get(client, path, f, t):
        asked = time_module.time()
        time_module.sleep(0.03)
        body = [{"robotId": "r1", "ts_ms": f + i, "receive_time_ms": f + i} for i in range(rows)]
        return body, asked, time_module.time()

    monkeypatch.setattr(poller, "_get", slow_get)
    monkeypatch.setattr(probes, "POLL_LIMIT", 5)
    poller.run()
    return poller


def test_a_slow_complete_poll_is_followed_by_the_next_at_once_not_by_an_equal_wait(
    monkeypatch,
) -> None:
    """The gap between polls is the poll figure's resolution: a poll slower than the
    cadence that returned its whole window is followed by the next without a wait."""
    poller = _slow_poller(monkeypatch, rows=2)
    assert poller.truncated_polls == 0 and poller.polls == 3
    assert poller._halt.waits == [0.0, 0.0, 0.0]
    assert len(poller.cycle_seconds) == 2 and all(c >= 0.06 for c in poller.cycle_seconds)


def test_a_poll_cut_at_the_row_limit_backs_off_as_long_as_it_took(monkeypatch) -> None:
    """A backlog wider than one read must not become a read load of its own: after a
    truncated poll the poller waits as long as the poll took."""
    poller = _slow_poller(monkeypatch, rows=5)
    assert poller.truncated_polls == 6
    assert all(w >= 0.06 for w in poller._halt.waits)


def test_without_latency_clients_a_small_fleet_is_judged_on_the_servers_timing_alone() -> None:
    """--no-latency-clients: up to 1,000 robots the push and poll bounds are left out (not
    measured) and the server-timed bound judges; above, they stay in, not held, so such a
    run never passes for one that held every bound."""
    from mapservice.bench.ingest.report import live_bounds

    unmeasured = _fleet_figures(
        sustained_events_per_s=1200.0, latency_pushed_p99_s=None, latency_polled_p99_s=None
    )
    small = live_bounds(1000, {**unmeasured, "stored_within_small_fleet_bound": 0.995}, False)
    assert [n for n, *_ in small if n.startswith("p99 by")] == []
    assert all(ok for *_, ok in small)
    slow = live_bounds(1000, {**unmeasured, "stored_within_small_fleet_bound": 0.95}, False)
    assert [n for n, _, _, ok in slow if not ok] == ["p99 publish -> stored (server)"]
    large = live_bounds(5000, _fleet_figures(latency_pushed_p99_s=0.1), False)
    assert sorted(n for n, _, _, ok in large if not ok) == [
        "p99 by the live push",
        "p99 by the poll",
    ]


def test_the_results_say_the_clients_figures_were_not_measured(capsys) -> None:
    """Without the latency clients the push and poll rows say why they are empty, and the
    unseen-events row is not judged."""
    out = printed_results(
        capsys,
        1000,
        60.0,
        latency_clients=False,
        latency_pushed_p99_s=None,
        latency_polled_p99_s=None,
        stored_within_small_fleet_bound=0.995,
        stored_latency_p99_s=0.25,
    )
    push = next(line for line in out.splitlines() if "p99 by the live push alone" in line)
    assert "not measured (--no-latency-clients)" in push and "MISSED" not in push
    assert "MISSED" not in out


def test_the_ingest_command_runs_the_latency_clients_unless_told_not_to() -> None:
    import argparse

    from mapservice.bench.cli import add_bench_parser

    parser = argparse.ArgumentParser()
    add_bench_parser(parser.add_subparsers(dest="command"))
    assert parser.parse_args(["bench", "ingest"]).latency_clients is True
    assert parser.parse_args(["bench", "ingest", "--no-latency-clients"]).latency_clients is False


def test_the_progress_line_claims_nothing_queryable_without_the_poller() -> None:
    """Without the latency clients nothing counts what is queryable: the progress line
    shows what was published, not "queryable 0"."""
    import time
    from types import SimpleNamespace

    from mapservice.bench.ingest.run import _status_line

    fleet = SimpleNamespace(stats=SimpleNamespace(poses=6000, chunks=0))
    line = _status_line(1, 1, "fleet", 1.0, 60, fleet, None, time.time() - 1)
    assert "published 6,000" in line and "queryable" not in line
