"""CPU seconds per stack component, the load generator, the latency probes and the rest
of the machine, sampled before and after the fleet runs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import psutil

from mapservice.bench.procstat import cpu_seconds


def _thread_cpu_seconds(native_id: int | None) -> float:
    if native_id is None:
        return 0.0
    for t in psutil.Process().threads():
        if t.id == native_id:
            return t.user_time + t.system_time
    return 0.0


class CpuMeter:
    """CPU seconds per stack component, this process and its latency probes' threads, and
    the machine."""

    def __init__(
        self, procs: dict, probe_native_ids: list[int | None], loadgen_pids: Sequence[int] = ()
    ) -> None:
        self.procs = {name: psutil.Process(p.pid) for name, p in procs.items()}
        self.probe_native_ids = probe_native_ids  # the latency poller's and listener's threads
        self.loadgen = [psutil.Process(pid) for pid in loadgen_pids]  # RawFleet's workers
        self.me = psutil.Process()

    def snapshot(self) -> dict:
        machine = psutil.cpu_times()

        def field(name: str) -> float:
            return getattr(machine, name, 0.0)  # fields vary by OS

        snap = {name: cpu_seconds(p) for name, p in self.procs.items()}
        me = self.me.cpu_times()
        snap["_bench_process"] = me.user + me.system
        snap["_poller_thread"] = sum(_thread_cpu_seconds(i) for i in self.probe_native_ids)
        snap["_loadgen_workers"] = sum(cpu_seconds(p) for p in self.loadgen)
        # Linux counts guest time inside user time, so it is not added again.
        snap["_machine_processes"] = field("user") + field("nice") + field("system")
        snap["_machine_irq"] = field("irq") + field("softirq")
        snap["_machine_steal"] = field("steal")  # taken by the hypervisor for other VMs
        snap["_wall"] = time.monotonic()
        return snap

    @staticmethod
    def percent(before: dict, after: dict, workers_cpu_s: float | None = None) -> dict:
        """Shares of one core; `workers_cpu_s`: the load fleet's workers' own count of their
        CPU time (they exit when the fleet is done, before `after` could sample them)."""
        wall = after["_wall"] - before["_wall"]
        pct = {k: 100.0 * (after[k] - before[k]) / wall for k in before if not k.startswith("_")}
        for name in [k for k in pct if k.startswith("gateway-")]:  # replicas count as the gateway
            pct["gateway"] += pct.pop(name)
        bench = 100.0 * (after["_bench_process"] - before["_bench_process"]) / wall
        poller = 100.0 * (after["_poller_thread"] - before["_poller_thread"]) / wall
        workers = (
            100.0
            * (
                workers_cpu_s
                if workers_cpu_s is not None
                else after.get("_loadgen_workers", 0.0) - before.get("_loadgen_workers", 0.0)
            )
            / wall
        )
        pct["stack_total"] = sum(pct.values())
        # The load generator: its worker processes (RawFleet) and its part of this process
        # (paho's RobotFleet; or RawFleet collecting the acknowledged messages).
        pct["loadgen"] = bench - poller + workers
        pct["loadgen_workers"] = workers
        pct["latency_probes"] = poller
        delta = {
            k: 100.0 * (after[k] - before[k]) / wall
            for k in ("_machine_processes", "_machine_irq", "_machine_steal")
        }
        # Whatever else ran on the machine meanwhile (other users' work competes for the cores).
        pct["other_processes"] = delta["_machine_processes"] - pct["stack_total"] - bench - workers
        pct["irq_softirq"] = delta["_machine_irq"]
        pct["steal"] = delta["_machine_steal"]
        pct["machine_busy_all_cores"] = sum(delta.values())
        pct["wall_s"] = wall
        return pct


def cpu_us_per_event(cpu_pct: dict, events: int, wall_s: float) -> dict:
    """Each component's CPU per published event, in µs: its share of a core over the
    fleet's wall time divided by the events published in it."""
    if not events or wall_s <= 0:
        return {}
    per_s = events / wall_s
    skip = ("other_processes", "irq_softirq", "steal", "machine_busy_all_cores", "wall_s")
    return {k: v * 1e4 / per_s for k, v in cpu_pct.items() if k not in skip}
