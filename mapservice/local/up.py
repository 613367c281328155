"""`mapservice up`: the whole service on this machine (local.stack), its addresses and
tokens on the console, simulated robots, and a supervisor that restarts what exits."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from mapservice.settings import Settings


def cmd_up(args) -> None:
    from rich.console import Console

    from mapservice.adapters.clock import SystemClock
    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.local import lifetime
    from mapservice.local.embedded import module_command
    from mapservice.local.private_dir import protect_data_dir
    from mapservice.local.stack import Stack
    from mapservice.local.up_output import log, print_addresses, step
    from mapservice.robot.map_upload import check_data_dir_map, check_map, upload_map_if_fresh
    from mapservice.runtime.logs import configure

    # Nothing `up` or its components write (secrets, logs, the broker's store, the history)
    # is readable by other users.
    os.umask(0o077)
    configure("INFO", "console", "up")
    # httpx logs every readiness poll (~20 `GET /readyz 503` while the server starts).
    logging.getLogger("httpx").setLevel(logging.WARNING)
    console = Console()
    # Ctrl-C stops everything even when started from a shell that ignores SIGINT for
    # background jobs (Python then keeps it ignored); SIGTERM stops the children too.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    if args.auth and args.mqtt_url:
        sys.exit(
            "mapservice up: --auth runs its own Mosquitto with robot identities; a broker "
            'given by --mqtt-url has its own authentication (README "Robot identities")'
        )
    from mapservice.local.embedded import default_mqtt_broker, mosquitto_installed

    # The embedded broker is Mosquitto when installed: it keeps a restarting gateway's QoS 1
    # messages (amqtt does not), and with --auth it is required: amqtt drops a client id's
    # session before it checks the credential, so it cannot keep robots' identities apart.
    if args.auth and not args.mqtt_url and not mosquitto_installed():
        sys.exit("mapservice up: --auth needs Mosquitto (`make system-deps` installs it)")
    broker = args.mqtt_url or default_mqtt_broker()
    if broker == "amqtt":
        console.print(
            "[yellow]Mosquitto is not installed: the embedded MQTT broker is amqtt, which "
            "does not keep QoS 1 messages for a restarting gateway (README, embedded "
            "mode). `make system-deps` installs Mosquitto.[/yellow]"
        )
    from mapservice.local.kafka_broker import embedded_choice
    from mapservice.settings import Settings

    # Under --auth the embedded Apache Kafka takes only the components' credential; tansu
    # (no Java) has no authentication, said below and in the README's limits.
    kafka_open = args.auth and embedded_choice(Settings().embedded_kafka) != "apache"
    if kafka_open:
        console.print(
            "[yellow]--auth on tansu: Kafka has no authentication there, so any local user "
            "can produce to it (Apache Kafka, with a Java runtime, requires the service's "
            "credential).[/yellow]"
        )
    stack = Stack(
        Path(args.data_dir),
        mqtt=broker,
        api_port=args.api_port,
        foxglove_port=args.foxglove_port,
        mqtt_port=args.mqtt_port if not args.mqtt_url else 0,
        kafka_port=args.kafka_port,
        mqtt_auth=args.auth,
        kafka_auth=args.auth and not kafka_open,
        tied_to_parent=True,
        apart=True,
    )
    other = stack.pid_file.running_up()
    if other is not None:
        sys.exit(
            f"mapservice up: another `mapservice up` (pid {other.pid}) runs on "
            f"{stack.data_dir}; stop it (Ctrl-C there, or `kill {other.pid}`) or pass "
            "another --data-dir"
        )
    leftovers = stack.pid_file.leftovers()
    if leftovers:
        log.warning(
            "the last `mapservice up` on this data dir ended without stopping its "
            "components; ending them",
            components=[f"{p.name} (pid {p.pid})" for p in leftovers],
            pid_file=str(stack.pid_file.path),
        )
        lifetime.end(leftovers)
    protect_data_dir(stack.data_dir)
    stack.start_guard()
    ros_map = load_ros_map(args.map)
    try:
        check_data_dir_map(stack.data_dir, ros_map)  # before the meta is published
        check_map(stack.settings(), ros_map, SystemClock().now_ms())  # the intake takes it
        had_history = (stack.data_dir / "clickhouse").exists()
    except ValueError as exc:
        sys.exit(f"mapservice up: {exc}")
    try:
        if not had_history and args.robots and args.history_days > 0:
            # Its own process: chDB lets one process open a directory, and the engine is
            # released only when the process that opened it ends.
            done = subprocess.run(
                module_command(
                    "mapservice.cli",
                    "demo-history",
                    "--data-dir",
                    str(stack.data_dir),
                    "--days",
                    str(args.history_days),
                    "--robots",
                    str(args.robots),
                    "--map",
                    str(args.map),
                ),
                preexec_fn=lifetime.die_with_parent,
            )
            if done.returncode != 0:
                raise RuntimeError(
                    "writing the demo history failed (see above); "
                    "`--history-days 0` starts without it"
                )
        kafka_name = embedded_kafka_intro(stack, console)
        robot_credentials = None
        if args.auth:
            # Before the broker starts, which reads them then: a running Mosquitto would have
            # to be restarted to read them (Stack.reload_mqtt says why never by SIGHUP).
            with step(console, "giving each simulated robot its MQTT credential"):
                # The /controller page drives a robot too: it needs one to publish as.
                robot_credentials = stack.robot_credentials(
                    simulated_robot_ids(args) + [CONTROLLER_ROBOT]
                )
        # Side by side where nothing waits on the other: a component's start is mostly its
        # interpreter importing, so started together they are up in the slowest one's time.
        with step(
            console, f"starting Kafka ({kafka_name}), the MQTT broker and the ClickHouse server"
        ):
            stack.start_brokers_and_clickhouse(meta_for(ros_map))
        # Processes apart, as the split deployment runs them: the history consumer never
        # shares a process (its CPU, memory, threads) with API reads and exports.
        with step(
            console,
            "starting the processors (creating the ClickHouse schema), the API and the "
            "MQTT-to-Kafka gateway, each its own process",
        ):
            stack.start_apart(gateway=True)
        with step(console, "publishing the map's chunks (fresh data dir only)"):
            uploaded = upload_map_if_fresh(
                stack.settings(), stack.data_dir, ros_map, SystemClock().now_ms(), had_history
            )
        if args.robots:
            # The shift simulator (robots on the map's free space, paths, batteries, pallets
            # and doors) unless the 2019 load test is asked for.
            stack.spawn(
                "sim",
                "sim",
                "--robots",
                str(args.robots),
                "--map",
                str(args.map),
                *(["--load-test"] if args.load_test else []),
                *(["--credentials", str(robot_credentials)] if robot_credentials else []),
            )
        rows: list[tuple[str, str]] = []  # the address table: (what, where)

        def row(name: str, value: str) -> None:
            rows.append((name, value))

        row("API", stack.api_url + "  (docs at /docs)")
        row(
            "MQTT (robots)",
            stack.mqtt_url
            + (
                "  (robot identities: anonymous clients refused; add a robot with `mapservice robot "
                f"add <robotId> --data-dir {stack.data_dir}`)"
                if args.auth
                else "  (anonymous)"
            ),
        )
        if broker in ("mosquitto", "amqtt"):
            row(
                "MQTT broker",
                f"Mosquitto, store in {stack.data_dir / 'mosquitto'}"
                if broker == "mosquitto"
                else "amqtt, no store (Mosquitto is not installed)",
            )
        if robot_credentials:
            row(
                "Robots' MQTT credentials",
                f"{robot_credentials} (the simulated robots' "
                f"and {CONTROLLER_ROBOT}'s: type its password on {stack.api_url}/controller)",
            )
        row(
            "Foxglove / Lichtblick",
            f"{stack.foxglove_url}  (live; {stack.foxglove_url}/replay: the week under the "
            "app's playback controls; docs/foxglove.md)",
        )
        row("MQTT WebSocket (browsers)", stack.mqtt_ws_url or "(none)")
        row(f"Kafka ({kafka_name})", f"127.0.0.1:{stack.kafka_port}  (" + kafka_keeps(stack) + ")")
        row(
            "ClickHouse",
            f"{stack.clickhouse_url}  (`mapservice clickhouse-server` over "
            f"{Settings(data_dir=stack.data_dir).resolved_clickhouse_dsn}; user default, password "
            f"in {stack.data_dir / 'secrets' / 'clickhouse-password'})",
        )
        row("Processors health", f"http://127.0.0.1:{stack.processors_health_port}/readyz")
        row(
            "SQL (analysts, read-only)",
            f"{stack.api_url}/clickhouse  user analyst, password "
            f"in {stack.data_dir / 'secrets' / 'analyst-password'} (docs/analysts.md)",
        )
        for name, where in api_token_rows(stack.settings()):
            row(name, where)
        row("Gateway health", f"http://127.0.0.1:{stack.health_port}/readyz")
        row(
            "Map",
            f"{args.map} ({ros_map.width} x {ros_map.height} px; "
            + (f"{uploaded} chunks published)" if uploaded else "as stored)"),
        )
        row(
            "Simulated robots",
            f"{args.robots} on {args.map}"
            + (" (2019 load test)" if args.load_test else " (shift simulator)"),
        )
        row("Logs", str(stack.log_dir))
        print_addresses(console, "mapservice is up", rows)
        console.print("Ctrl-C stops everything; `make up` again resumes on the same data.")
        if args.open_browser:
            import webbrowser

            webbrowser.open(stack.api_url + "/")
        supervise(stack, console, args.restart_base_s)
    except KeyboardInterrupt:
        console.print("stopping...")
    except RuntimeError as exc:
        console.print(f"[red]{exc}[/red]")
        sys.exit(1)
    finally:
        stack.stop()


def embedded_kafka_intro(stack, console) -> str:
    """Which Kafka `up` runs (said on the console, with what the tansu fallback costs);
    fetches the Apache Kafka jars first, with progress, when they are not cached yet, and
    makes their class-data archive when there is none."""
    from mapservice.local import kafka_broker

    if stack.kafka == "tansu":
        why = (
            "no Java runtime found (`make up` installs it as root)"
            if kafka_broker.java_binary() is None
            else "MAPSERVICE_EMBEDDED_KAFKA=tansu"
        )
        console.print(
            f"[yellow]Kafka is tansu: {why}. {kafka_broker.TANSU_COST}; use Apache "
            "Kafka for anything longer than a working session (README, embedded "
            "mode).[/yellow]"
        )
        return "tansu, in memory"
    version = kafka_broker.kafka_version()
    settings = stack.settings()
    jars = settings.kafka_jars_dir or kafka_broker.default_jars_dir()
    if not (jars / ".complete").exists():
        console.print(f"fetching Apache Kafka {version}'s jars with Maven into {jars} (once)...")
        kafka_broker.ensure_jars(
            jars, progress=lambda line: console.print(f"  {line}", highlight=False)
        )
    java = kafka_broker.java_binary()
    if java is not None:
        kafka_broker.class_sharing(java, jars / "libs", wait=True, progress=console.print)
    return f"Apache Kafka {version}"


def kafka_keeps(stack) -> str:
    if stack.kafka == "tansu":
        return "no retention; a restart loses what it held"
    settings = stack.settings()
    return (
        f"log in {stack.data_dir / 'kafka'}, kept {settings.embedded_kafka_retention_hours} h "
        f"and at most {settings.embedded_kafka_retention_bytes // 1024**2} MB a partition"
    )


def api_token_rows(settings: Settings) -> list[tuple[str, str]]:
    """`up`'s table rows saying where each API token is and what it opens; generates the
    ones local mode makes (the server reads the same files)."""
    from mapservice.runtime.secrets import (
        ADMIN_TOKEN_FILE,
        OPERATOR_TOKEN_FILE,
        READER_TOKEN_FILE,
        WRITER_TOKEN_FILE,
        secrets_dir,
        with_local_api_secrets,
    )
    from mapservice.settings import token_list

    with_local_api_secrets(settings)
    rows = []
    for title, field, file, use in (
        (
            "API writer token (robots)",
            "api_writer_tokens",
            WRITER_TOKEN_FILE,
            "REST writes; `mapservice robot` and `map upload` read it from there",
        ),
        ("API admin token", "admin_token", ADMIN_TOKEN_FILE, "deletes, changing the map"),
        (
            "API operator token",
            "api_operator_tokens",
            OPERATOR_TOKEN_FILE,
            "editing points of interest and zones",
        ),
        ("API reader token", "api_reader_tokens", READER_TOKEN_FILE, "reads"),
    ):
        if field == "api_reader_tokens" and settings.api_read_access == "open":
            continue
        where = (
            f"MAPSERVICE_{field.upper()}"
            if token_list(getattr(settings, field))
            else str(secrets_dir(settings.data_dir) / file)
        )
        rows.append((title, f"{where}  ({use}: 'Authorization: Bearer <token>')"))
    rows.append(
        (
            "API reads",
            "open (MAPSERVICE_API_READ_ACCESS=open)"
            if settings.api_read_access == "open"
            else "need a token",
        )
    )
    return rows


# The robot id the /controller page drives by default (replay-ui/src/Controller.vue).
CONTROLLER_ROBOT = "controller-1"


def simulated_robot_ids(args) -> list[str]:
    """The ids `mapservice sim` gives its robots (shift simulator or 2019 load test)."""
    from mapservice.robot.loadgen import fleet_robot_id
    from mapservice.robot.sim import sim_robot_id

    robot_id = fleet_robot_id if args.load_test else sim_robot_id
    return [robot_id("sim", i) for i in range(args.robots)]


def supervise(stack, console, base_s: float = 1.0) -> None:
    """Runs until Ctrl-C: a component that exits is restarted with backoff, not the end."""
    from mapservice.local.supervisor import Supervisor

    supervisor = Supervisor(
        stack.is_alive,
        {name: (lambda n=name: stack.restart(n)) for name in list(stack.procs)},
        report=lambda message: console.print(f"[yellow]{message}; see {stack.log_dir}[/yellow]"),
        base_s=base_s,
    )
    while True:
        supervisor.check()
        if stack.reload_mqtt_if_files_changed():
            console.print(
                "robots' MQTT credentials changed: Mosquitto restarted to read them "
                "(its queued messages kept)"
            )
        time.sleep(0.5)
