"""Unit tests of the ingest benchmark's latency arithmetic (no brokers)."""
from mapservice.bench.ingest import INF, _latencies, _stage_latencies, queryable_times

KEY = ("pose", "r1", 1_700_000_000_000)


def test_sub_millisecond_hop_to_the_gateway_is_never_negative() -> None:
    """The gateway stamps floored milliseconds; a publish 0.4 ms before it, in the same
    millisecond, counts as 0 s to the gateway, not as a negative time."""
    published = 1_700_000_000.1236  # 0.6 ms into millisecond ...123
    stages = _stage_latencies({KEY: 1_700_000_000_123 / 1000}, {KEY: published + 0.25}, {KEY: published})
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
    from mapservice.bench.ingest import storage_verdict

    assert storage_verdict(20, 9e6) is None
    assert storage_verdict(120, 1.4e6) is True
    assert storage_verdict(120, 9e6) is False
