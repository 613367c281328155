"""`mapservice bench sink`: CPU per event of the processors' history path.

Each run is a fresh process: it fills a pose topic on the embedded broker `up` would run
(Apache Kafka where Java is, else tansu; MAPSERVICE_EMBEDDED_KAFKA picks) with N events,
then drains it through the processors' HistoryConsumer (confluent-kafka KafkaBatchSource,
decode, store, commit) into a store that only counts, and reports the CPU time (user +
system of the whole process) and wall time from the first stored event to the last: the
cost of the path itself, without ClickHouse's insert.
"""

from __future__ import annotations

import asyncio
import json
import os
import resource
import statistics
import subprocess
import time
from contextlib import ExitStack
from pathlib import Path

from mapservice.bench.workdir import bench_data_dir

WAYS = ("batch",)


def add_parser(kinds) -> None:
    p = kinds.add_parser("sink", help="CPU per event of the processors' history path")
    p.add_argument(
        "--events", type=int, default=60_000, help="pose events published and then consumed per run"
    )
    p.add_argument("--repeat", type=int, default=3, help="runs per way; medians are reported")
    p.add_argument("--json", default=None, help="write the results as JSON to this file")
    p.add_argument("--one", choices=WAYS, help=argparse_hidden())
    p.set_defaults(func=main)


def argparse_hidden():
    import argparse

    return argparse.SUPPRESS


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


class BenchError(Exception):
    """A run that cannot measure anything; the message says what to change."""


class _Counter:
    n = 0


async def _one(way: str, events: int) -> dict:
    from mapservice.adapters.kafka_publisher import KafkaPublisher
    from mapservice.adapters.kafka_topics import ensure_topics
    from mapservice.core.events import PoseReported, encode, kafka_key, make_envelope
    from mapservice.local import kafka_broker
    from mapservice.local.embedded import free_port, stop
    from mapservice.settings import Settings
    from mapservice.testing.memory_store import MemoryStore

    class CountingStore(MemoryStore):
        def append_events(self, batch) -> None:
            _Counter.n += len(batch)

    port = free_port()
    cleanup = ExitStack()  # closed last in, first out: producer, broker, data dir
    try:
        data = cleanup.enter_context(bench_data_dir(None, "bench-sink-"))
        settings = Settings(kafka_bootstrap=f"127.0.0.1:{port}", data_dir=data)
        choice = kafka_broker.embedded_choice(settings.embedded_kafka)
        broker = kafka_broker.start_embedded(
            choice,
            data,
            port,
            settings,
            log_file=cleanup.enter_context(
                open(os.environ.get("BENCH_SINK_BROKER_LOG", os.devnull), "wb")
            ),
        )
        cleanup.callback(stop, broker)
        ensure_topics(settings)
        pub = KafkaPublisher(settings, "bench-sink")
        cleanup.callback(pub.close)
        # Recent instants: the sink stores nothing older than the retention at its clock.
        t0 = int(time.time() * 1000) - (events // 1000 + 1) * 1000
        for i in range(events):
            payload = PoseReported(
                position=(i % 50 * 0.1, 1.0, 0.0),
                orientation=(0.0, 0.0, 0.0, 1.0),
                battery_level=80.0,
            )
            e = make_envelope(
                f"robot-{i % 1000:04d}", t0 + i // 1000 * 1000, t0 + i // 1000 * 1000 + 20, payload
            )
            pub.publish(settings.topic_pose_events, kafka_key(e), encode(e), lambda err: None)
            if i % 5000 == 0:
                pub.poll(0)
        if pub.flush(60):
            raise RuntimeError("could not fill the topic")
        store = CountingStore()
        stopping = asyncio.Event()
        from mapservice.adapters.kafka_batch_source import KafkaBatchSource
        from mapservice.processors.history_consumer import HistoryConsumer
        from mapservice.processors.sink import HistorySink

        source = KafkaBatchSource(settings, [settings.topic_pose_events], "bench-sink")
        consumer = HistoryConsumer(
            source,
            HistorySink(store),
            None,
            settings.sink_batch_size,
            settings.sink_batch_seconds,
            min_batch_seconds=settings.sink_batch_min_seconds,
            views_seconds=settings.sink_views_seconds,
        )
        source.on_assigned = consumer.on_assigned
        task = asyncio.create_task(consumer.run(stopping))
        first = None
        deadline = time.monotonic() + 600
        while _Counter.n < events and time.monotonic() < deadline:
            await asyncio.sleep(0.005)
            if first is None and _Counter.n:
                first = (time.monotonic(), _cpu_s(), _Counter.n)
        if first is None:
            raise BenchError(f"no event reached the sink within 600 s of {events:,} published")
        wall, cpu = time.monotonic() - first[0], _cpu_s() - first[1]
        counted = _Counter.n - first[2]
        if counted <= 0 or wall <= 0:
            # Timing starts at the first batch (the group join before it is not the sink's
            # cost), so the events after it are what is measured.
            raise BenchError(
                f"all {events:,} events arrived in the first batch: nothing left "
                "to time; pass more --events (e.g. the default 60,000)"
            )
        return {
            "way": way,
            "events": counted,
            "wall_s": round(wall, 3),
            "cpu_s": round(cpu, 3),
            "cpu_us_per_event": round(cpu / counted * 1e6, 1),
            "events_per_s": round(counted / wall),
            "complete": _Counter.n >= events,
            "broker": choice,
            "task": bool(task),
        }
    finally:
        cleanup.close()


def main(args) -> None:
    if args.one:
        try:
            result = asyncio.run(_one(args.one, args.events))
        except BenchError as exc:
            print(f"ERROR {exc}", flush=True)
            os._exit(2)
        print("RESULT " + json.dumps(result), flush=True)
        os._exit(0)  # librdkafka's threads need not be waited for
    from mapservice.bench.machine import machine_facts
    from mapservice.local.embedded import module_command

    runs: dict[str, list[dict]] = {w: [] for w in WAYS}
    for i in range(args.repeat):
        for way in WAYS:
            out = subprocess.run(
                module_command(
                    "mapservice.cli",
                    "bench",
                    "sink",
                    "--one",
                    way,
                    "--events",
                    str(args.events),
                ),
                capture_output=True,
                text=True,
                timeout=900,
            )
            line = next((x for x in out.stdout.splitlines() if x.startswith("RESULT ")), None)
            error = next((x for x in out.stdout.splitlines() if x.startswith("ERROR ")), None)
            if error is not None:
                raise SystemExit(f"mapservice bench sink: {error[6:]}")
            if line is None:
                raise SystemExit(f"{way} run failed:\n{out.stderr[-3000:]}".rstrip())
            result = json.loads(line[7:])
            runs[way].append(result)
            print(
                f"run {i + 1}/{args.repeat} {way:5}: {result['cpu_us_per_event']:7.1f} µs CPU/event, "
                f"{result['events_per_s']:,} events/s (broker: {result['broker']})",
                flush=True,
            )
    summary = {
        w: {
            "cpu_us_per_event_median": statistics.median(r["cpu_us_per_event"] for r in rs),
            "events_per_s_median": statistics.median(r["events_per_s"] for r in rs),
        }
        for w, rs in runs.items()
    }
    print(
        f"median: {summary['batch']['cpu_us_per_event_median']} µs CPU per event, "
        f"{summary['batch']['events_per_s_median']:,} events/s"
    )
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "machine": machine_facts(),
                    "events": args.events,
                    "summary": summary,
                    "runs": runs,
                },
                indent=2,
            )
        )
