"""`mapservice bench`: measured, repeatable runs (results go to BENCHMARKS.md)."""

from __future__ import annotations

import argparse

from mapservice.bench.workdir import DATA_DIR_HELP


def add_bench_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    bench = sub.add_parser("bench", help="benchmarks")
    kinds = bench.add_subparsers(dest="kind", required=True)
    ingest = kinds.add_parser("ingest", help="the 2019 load test through the whole pipeline")
    ingest.add_argument(
        "--robots", type=int, default=20, help="simulated robots (each a pose a second)"
    )
    ingest.add_argument(
        "--seconds", type=float, default=60, help="how long the fleet publishes per run"
    )
    ingest.add_argument("--mqtt", default="mosquitto", help="mosquitto, amqtt or an mqtt:// URL")
    ingest.add_argument("--data-dir", default=None, help=DATA_DIR_HELP)
    ingest.add_argument("--repeat", type=int, default=1, help="runs; medians are reported")
    ingest.add_argument("--json", default=None, help="write the results as JSON to this file")
    ingest.add_argument(
        "--poll-interval",
        type=float,
        default=0.1,
        help="seconds between the latency poller's API reads",
    )
    ingest.add_argument(
        "--latency-clients",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="run the live listener and the poller (a live UI and an analyst reading every "
        "event through the API, on this machine); --no-latency-clients leaves them out to "
        "measure what they cost the stack: publish -> stored is then timed by the server "
        "alone, and the push and poll bounds are not measured (up to 1,000 robots the "
        "server-timed bound judges the latency; above, the run cannot hold every bound)",
    )
    ingest.add_argument(
        "--loadgen",
        choices=["raw", "paho"],
        default="raw",
        help="the load fleet: raw = pre-encoded MQTT packets from worker processes "
        "(bench/fleet/rawfleet.py), paho = one paho client (robot/loadgen.py: its own "
        "CPU limits the fleet long before the stack's)",
    )
    ingest.add_argument(
        "--aligned-chunks",
        action="store_true",
        help="every robot sends its chunk (one per five poses) after the same pose: "
        "the fleet's chunks burst in one second of five (a stress schedule; real "
        "robots start at different moments); default: spread evenly, robot "
        "i's cycle offset by i poses",
    )
    ingest.add_argument(
        "--loadgen-processes",
        type=int,
        default=None,
        help="raw load fleet: worker processes (default: one per 4,000 robots)",
    )
    ingest.add_argument(
        "--gateways",
        type=int,
        default=1,
        help="gateway processes; more than one share the robots' topics through "
        "an MQTT shared subscription (as the gateway Deployment's replicas "
        "do); their CPU is reported together as the gateway's",
    )
    ingest.add_argument(
        "--find-ceiling",
        action="store_true",
        help="step the fleet up from --robots by --ceiling-step (each step --repeat "
        "runs, judged on their medians) until a step misses a bound; states the "
        "largest fleet that held them",
    )
    ingest.add_argument(
        "--ceiling-step", type=int, default=1000, help="robots added per --find-ceiling step"
    )
    ingest.add_argument(
        "--ceiling-max",
        type=int,
        default=10_000,
        help="--find-ceiling stops at this fleet even if it still holds",
    )
    ingest.add_argument(
        "--workload",
        choices=["2019", "vda5050"],
        default="2019",
        help="2019: each robot a pose a second and a chunk every 5 s; vda5050: "
        "each --robots a VDA 5050 vehicle, a state a second and a "
        "visualization at 5 Hz (mapservice/bench/vda_fleet.py)",
    )
    ingest.add_argument(
        "--kafka",
        choices=["auto", "apache", "tansu", "both"],
        default="auto",
        help="the embedded Kafka: apache (a KRaft node from the Apache Kafka "
        "jars), tansu (in memory), auto (MAPSERVICE_EMBEDDED_KAFKA: apache "
        "where Java is), or both: each --repeat round runs the workload on "
        "Apache Kafka and on tansu and prints them side by side (CPU per "
        "event per component, latency, memory; bench/compare.py)",
    )
    ingest.add_argument(
        "--compare",
        action="append",
        metavar="NAME=KEY=VALUE,...",
        help="given twice: run the workload on two variants of the stack, interleaved "
        "round by round (--repeat rounds), and report each measure's medians with the "
        "second's over the first's; a variant's KEY=VALUE pairs are settings of the "
        "components (MAPSERVICE_...=...), kafka=apache|tansu, or python=PATH (another "
        "checkout's Python: its code runs the components); bench/compare.py",
    )
    ingest.add_argument(
        "--profile",
        metavar="DIR",
        default=None,
        help="while the fleet runs, sample each Python component (the gateways, serve) "
        "with py-spy (`pip install py-spy`; root or CAP_SYS_PTRACE) and write a flame graph "
        "of its CPU to DIR/<component>-run<N>.svg (with --compare, "
        "<component>-<variant>-run<N>.svg); the brokers (Java, C) are not sampled",
    )
    ingest.set_defaults(func=_run_ingest)

    from mapservice.bench.timetravel import add_parser as add_timetravel_parser

    add_timetravel_parser(kinds)

    from mapservice.bench.sink import add_parser as add_sink_parser

    add_sink_parser(kinds)

    from mapservice.bench.ui import add_parser as add_ui_parser

    add_ui_parser(kinds)

    from mapservice.bench.soak import add_parser as add_soak_parser

    add_soak_parser(kinds)

    from mapservice.bench.group_protocol import add_parser as add_group_protocol_parser

    add_group_protocol_parser(kinds)

    from mapservice.bench.kafka_start import add_parser as add_kafka_start_parser

    add_kafka_start_parser(kinds)

    from mapservice.bench.incidents import add_parser as add_incidents_parser

    add_incidents_parser(kinds)

    from mapservice.bench.fanout import add_parser as add_fanout_parser

    add_fanout_parser(kinds)

    from mapservice.bench.foxglove import add_parser as add_foxglove_parser

    add_foxglove_parser(kinds)


def _run_ingest(args: argparse.Namespace) -> None:
    if args.kafka == "both" or getattr(args, "compare", None):
        from mapservice.bench.compare import main
    else:
        from mapservice.bench.ingest.command import main
    if args.kafka == "auto":
        args.kafka = ""  # the stacks follow MAPSERVICE_EMBEDDED_KAFKA
    main(args)
