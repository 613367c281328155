"""Unit tests of the ingest benchmark's latency arithmetic (no brokers)."""
from types import SimpleNamespace

from mapservice.bench_ingest import _stage_latencies


def test_sub_millisecond_hop_to_the_gateway_is_never_negative() -> None:
    """The gateway stamps floored milliseconds; a publish 0.4 ms before it, in the same
    millisecond, counts as 0 s to the gateway, not as a negative time."""
    key = ("pose", "r1", 1_700_000_000_000)
    published = 1_700_000_000.1236  # 0.6 ms into millisecond ...123
    poller = SimpleNamespace(received_at={key: 1_700_000_000_123 / 1000},
                             first_seen={key: published + 0.25})
    stages = _stage_latencies(poller, {key: published})
    assert stages["publish_to_gateway_p50_s"] == 0.0
    assert abs(stages["gateway_to_queryable_p50_s"] - 0.2506) < 1e-6


def test_stages_split_the_time_at_the_gateway_receive_stamp() -> None:
    """Publish -> gateway plus gateway -> queryable adds up to publish -> queryable,
    to within the millisecond the gateway's stamp drops."""
    key = ("chunk", "r2", 1)
    published = 1000.0
    poller = SimpleNamespace(received_at={key: 1000.120}, first_seen={key: 1001.5})
    stages = _stage_latencies(poller, {key: published})
    total = stages["publish_to_gateway_p50_s"] + stages["gateway_to_queryable_p50_s"]
    assert abs(stages["publish_to_gateway_p50_s"] - 0.120) < 1e-6
    assert abs(total - 1.5) < 1e-6
