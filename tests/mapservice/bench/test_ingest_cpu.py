"""Unit tests of the ingest benchmark's CPU meter: whose CPU counts as the stack's, the load
generator's or the probes', and CPU per event."""

from mapservice.bench.ingest.cpu import CpuMeter, cpu_us_per_event

# Every counter a CpuMeter snapshot holds, at zero.
ZERO = {
    "gateway": 0.0,
    "_bench_process": 0.0,
    "_poller_thread": 0.0,
    "_loadgen_workers": 0.0,
    "_machine_processes": 0.0,
    "_machine_irq": 0.0,
    "_machine_steal": 0.0,
    "_wall": 0.0,
}


def test_cpu_per_event_divides_each_components_share_by_the_event_rate() -> None:
    """50 % of a core at 5,000 events/s is 100 µs per event; machine-wide figures are left out."""
    per_event = cpu_us_per_event(
        {"gateway": 50.0, "loadgen": 10.0, "other_processes": 80.0, "wall_s": 60.0}, 300_000, 60.0
    )
    assert per_event == {"gateway": 100.0, "loadgen": 20.0}
    assert cpu_us_per_event({"gateway": 50.0}, 0, 60.0) == {}


def test_cpu_meter_counts_load_fleet_workers_as_load_generator_not_stack() -> None:
    """Worker processes' CPU goes to the load generator and stays out of the stack's total."""
    zero = dict(ZERO)
    after = {
        **zero,
        "gateway": 5.0,
        "_bench_process": 2.0,
        "_poller_thread": 1.0,
        "_loadgen_workers": 3.0,
        "_machine_processes": 12.0,
        "_wall": 10.0,
    }
    pct = CpuMeter.percent(zero, after)
    assert pct["stack_total"] == 50.0 and pct["loadgen"] == 40.0 and pct["loadgen_workers"] == 30.0
    assert pct["latency_probes"] == 10.0 and pct["other_processes"] == 20.0


def test_cpu_meter_takes_the_workers_own_cpu_count_when_given() -> None:
    """Workers that exited before the last sample report their CPU themselves: that counts."""
    zero = dict(ZERO)
    after = {**zero, "_loadgen_workers": -4.0, "_machine_processes": 1.0, "_wall": 10.0}
    assert CpuMeter.percent(zero, after, workers_cpu_s=1.0)["loadgen_workers"] == 10.0


def test_cpu_meter_counts_gateway_replicas_as_the_gateway() -> None:
    """A second gateway process's CPU is added to the gateway's, once."""
    zero = {**ZERO, "gateway-2": 0.0}
    after = {**zero, "gateway": 2.0, "gateway-2": 3.0, "_machine_processes": 5.0, "_wall": 10.0}
    pct = CpuMeter.percent(zero, after)
    assert pct["gateway"] == 50.0 and "gateway-2" not in pct and pct["stack_total"] == 50.0
