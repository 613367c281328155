"""The soak's arithmetic: growth per hour by least squares after the start-up tenth, tansu's
growth expected and reported per event, every other component's growth bounded."""

from __future__ import annotations

import pytest

from mapservice.bench.soak import growth_per_hour, settle, summarize


def sample(t_s: float, rss: dict[str, float], stored: int) -> dict:
    return {
        "t_s": t_s,
        "rss_mb": rss,
        "cpu_percent": dict.fromkeys(rss, 10.0),
        "published": stored,
        "stored": stored,
        "dead_letters": 0,
        "freshness_s": 1.0,
    }


def test_growth_per_hour_is_the_least_squares_slope() -> None:
    """A line rising 1 MB per minute grows 60 MB per hour; two points are too few."""
    assert growth_per_hour([0, 60, 120, 180], [100, 101, 102, 103]) == pytest.approx(60)
    assert growth_per_hour([0, 60], [1, 2]) is None


def test_settle_drops_the_first_tenth_of_the_run() -> None:
    """Start-up samples (the first tenth of the run) do not count toward growth."""
    samples = [sample(t, {"gateway": 1.0}, 0) for t in (0, 100, 500, 1000)]
    assert [s["t_s"] for s in settle(samples)] == [100, 500, 1000]


def test_summary_bounds_every_component_but_tansu_and_reports_tansu_per_event() -> None:
    """A gateway growing 60 MB/h breaks a 20 MB/h bound; tansu's growth is expected and
    priced per stored event (10 events/s, 36 MB/h -> 1,000 bytes per event)."""
    samples = [
        sample(t, {"gateway": 50 + t / 60, "kafka": 100 + t / 100, "server": 200.0}, int(t * 10))
        for t in range(0, 3601, 60)
    ]
    s = summarize(samples, minutes=60, max_growth_mb_per_h=20)
    assert s["representative"] is True
    assert s["components"]["gateway"]["growth_bounded"] is False
    assert s["components"]["server"]["growth_bounded"] is True
    assert s["components"]["kafka"]["growth_bounded"] is None
    assert s["bounded"] is False
    assert s["events_per_s"] == pytest.approx(10)
    assert s["kafka_bytes_per_event"] == pytest.approx(1000)
    assert s["kafka_mb_per_week"] == pytest.approx(36 * 24 * 7)


def test_summary_shows_cpu_at_the_start_and_at_the_end() -> None:
    """A component whose CPU share rises from 10 % to 40 % over the run reports both ends."""
    samples = [sample(t, {"kafka": 20.0}, t) for t in range(0, 3601, 60)]
    for i, s in enumerate(samples):
        s["cpu_percent"]["kafka"] = 10.0 + 30.0 * i / (len(samples) - 1)
    c = summarize(samples, minutes=60, max_growth_mb_per_h=20)["components"]["kafka"]
    assert c["cpu_start_percent"] < 15 and c["cpu_end_percent"] > 35


def test_a_run_under_an_hour_is_not_representative() -> None:
    """Ten minutes of samples are summarized but flagged as not representative."""
    samples = [sample(t, {"gateway": 50.0}, t) for t in range(0, 601, 30)]
    assert summarize(samples, minutes=10, max_growth_mb_per_h=20)["representative"] is False


def test_summary_splits_serves_memory_into_clickhouse_and_python() -> None:
    """ClickHouse's tracked memory growing 6 MB/h and flat Python blocks are each reported with their growth."""
    samples = [
        dict(
            sample(t, {"server": 500.0}, t),
            serve_inside={"chdb_mb": 100 + t / 600, "python_blocks_k": 300.0},
        )
        for t in range(0, 3601, 60)
    ]
    inside = summarize(samples, minutes=60, max_growth_mb_per_h=20)["serve_inside"]
    assert inside["chdb_mb"]["growth_per_h"] == pytest.approx(6)
    assert inside["python_blocks_k"]["growth_per_h"] == pytest.approx(0)


def test_growth_is_judged_on_anonymous_memory_where_it_was_sampled() -> None:
    """Resident file pages growing 60 MB/h (a mapped library paging in) with flat anonymous memory is bounded; anonymous growth is not."""

    def run(anon_slope: float) -> dict:
        samples = [
            dict(
                sample(t, {"server": 500 + t / 60}, t),
                anon_mb={"server": 250 + anon_slope * t / 3600},
            )
            for t in range(0, 3601, 60)
        ]
        return summarize(samples, minutes=60, max_growth_mb_per_h=20)["components"]["server"]

    flat = run(0)
    assert flat["growth_mb_per_h"] == pytest.approx(60) and flat[
        "anon_growth_mb_per_h"
    ] == pytest.approx(0)
    assert flat["growth_bounded"] is True
    assert run(30)["growth_bounded"] is False


def test_apache_kafkas_memory_is_judged_and_its_log_priced_per_event() -> None:
    """On Apache Kafka (a bounded heap) the broker's growth is judged like any component's,
    not excused as tansu's is, and its log's growth on disk is priced per stored event
    (10 events/s, 18 MB/h on disk -> 500 bytes per event)."""
    samples = [
        dict(
            sample(t, {"kafka": 300 + t / 60, "server": 200.0}, int(t * 10)),
            disk_mb={"kafka_log": 1 + t / 200},
        )
        for t in range(0, 3601, 60)
    ]
    apache = summarize(samples, minutes=60, max_growth_mb_per_h=20, kafka="apache")
    assert apache["components"]["kafka"]["growth_bounded"] is False
    assert apache["bounded"] is False
    assert "kafka_bytes_per_event" not in apache  # memory is not where Apache Kafka keeps records
    assert apache["disk"]["kafka_log"]["growth_mb_per_h"] == pytest.approx(18)
    assert apache["disk"]["kafka_log"]["bytes_per_event"] == pytest.approx(500)
    tansu = summarize(samples, minutes=60, max_growth_mb_per_h=20, kafka="tansu")
    assert tansu["components"]["kafka"]["growth_bounded"] is None
    assert tansu["kafka_bytes_per_event"] == pytest.approx(1000 * 60 / 36)
