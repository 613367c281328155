"""`mapservice`: run the whole service, one component, simulated robots or a benchmark."""

from __future__ import annotations

import argparse
import logging
import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from mapservice.robot import DEFAULT_MAP
from mapservice.settings import Settings
from mapservice.runtime.heap import freeze_startup_heap
from mapservice.runtime.startup import settings_for


def cmd_gateway(args) -> None:
    from mapservice.ingest.gateway import run_gateway
    from mapservice.adapters.kafka_topics import ensure_topics

    settings = settings_for("gateway")
    ensure_topics(settings)
    freeze_startup_heap()
    run_gateway(settings, args.health_port)


def cmd_serve(args, processors: bool = True, api: bool = True, component: str = "server") -> None:
    from mapservice.server import serve

    settings = settings_for(component)
    asyncio.run(serve(settings, processors=processors, api=api,
                      health_port=getattr(args, "health_port", None)))


def cmd_migrate(args) -> None:
    from mapservice.adapters.clickhouse.migrations import MigrationChanged, MigrationLocked
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION

    settings = settings_for("migrate")
    store = ClickHouseStore.from_settings(settings)
    log = logging.getLogger("mapservice.migrate")
    try:
        if args.break_lock:
            log.info("migration lock %s", "dropped" if store.break_migration_lock() else "was not held")
        before = store.schema_version()
        version = store.migrate(lock_timeout_s=args.lock_timeout_s)
    except (MigrationLocked, MigrationChanged) as exc:
        sys.exit(f"mapservice migrate: {exc}")
    finally:
        store.close()
    log.info("schema of %s at version %d (was %d; this release: %d)", settings.clickhouse_database,
             version, before, SCHEMA_VERSION)


def cmd_clickhouse_server(args) -> None:
    import uvicorn

    from mapservice.sql.apps import server_app

    settings = settings_for("clickhouse-server")
    app = server_app(settings, read_write=args.read_write)
    log = logging.getLogger("mapservice.clickhouse-server")
    log.info("ClickHouse HTTP interface over %s on http://%s:%d (%s)", app.state.chdb_path,
             args.host, args.port, "read-write" if args.read_write else "read-only")
    uvicorn.run(app, host=args.host, port=args.port, log_config=None, log_level=None,
                access_log=False)


def cmd_sql(args) -> None:
    import httpx

    from mapservice.sql.credentials import analyst_password

    settings = Settings(data_dir=Path(args.data_dir)) if args.data_dir else Settings()
    password = args.password or analyst_password(settings)
    if not password:
        sys.exit("mapservice sql: no analyst password: pass --password or set "
                 "MAPSERVICE_ANALYST_PASSWORD")
    query = args.query if args.query != "-" else sys.stdin.read()
    try:
        with httpx.stream("POST", args.url.rstrip("/") + "/", content=query.encode(),
                          params={"default_format": args.format},
                          auth=(args.user or settings.analyst_username, password),
                          timeout=settings.analyst_max_execution_s + 30) as reply:
            if reply.status_code != 200:
                sys.exit(reply.read().decode(errors="replace").strip())
            for chunk in reply.iter_bytes():
                sys.stdout.buffer.write(chunk)
    except httpx.HTTPError as exc:
        sys.exit(f"mapservice sql: cannot reach {args.url} ({exc}); is the service running "
                 "(`make up`)? --url points elsewhere")


def cmd_export(args) -> None:
    import httpx

    if args.dataset == "replay":
        url, params, ext = f"{args.api.rstrip('/')}/api/v1/exports/replay.mcap", {}, "mcap"
    else:
        url = f"{args.api.rstrip('/')}/api/v1/exports/tables/{args.dataset}"
        params, ext = {"format": args.format}, args.format
        if args.robot:
            params["robotId"] = args.robot
    params.update({"from": args.from_, "to": args.to})
    out = Path(args.out or f"{args.dataset}.{ext}")
    from mapservice.robot.api_client import writer_token

    # Exports are reads: open by default; where reads need a token, the robot-side one
    # (MAPSERVICE_API_TOKEN, or the one `up` generated) is sent.
    token = writer_token()
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        with httpx.stream("GET", url, params=params, timeout=600, headers=headers) as reply:
            if reply.status_code != 200:
                sys.exit(f"mapservice export: {reply.status_code} {reply.read().decode(errors='replace')}")
            with out.open("wb") as file:
                for chunk in reply.iter_bytes():
                    file.write(chunk)
    except httpx.HTTPError as exc:
        sys.exit(f"mapservice export: cannot reach {args.api} ({exc}); is the service running "
                 "(`make up`)? --api points elsewhere")
    print(f"wrote {out} ({out.stat().st_size:,} bytes)")


def cmd_up(args) -> None:
    from rich.console import Console

    from mapservice.local import lifetime
    from mapservice.local.up_output import log, print_addresses, step
    from mapservice.runtime.logs import configure
    from mapservice.adapters.clock import SystemClock
    from mapservice.robot.map_upload import check_data_dir_map, upload_map_if_fresh
    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.local.stack import Stack

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
        sys.exit("mapservice up: --auth runs its own Mosquitto with robot identities; a broker "
                 "given by --mqtt-url has its own authentication (README \"Robot identities\")")
    from mapservice.local.embedded import default_mqtt_broker, mosquitto_installed

    # The embedded broker is Mosquitto when installed: it keeps a restarting gateway's QoS 1
    # messages (amqtt does not), and with --auth it is required: amqtt drops a client id's
    # session before it checks the credential, so it cannot keep robots' identities apart.
    if args.auth and not args.mqtt_url and not mosquitto_installed():
        sys.exit("mapservice up: --auth needs Mosquitto (`make system-deps` installs it)")
    broker = args.mqtt_url or default_mqtt_broker()
    if broker == "amqtt":
        console.print("[yellow]Mosquitto is not installed: the embedded MQTT broker is amqtt, which "
                      "does not keep QoS 1 messages for a restarting gateway (README, embedded "
                      "mode). `make system-deps` installs Mosquitto.[/yellow]")
    stack = Stack(Path(args.data_dir), mqtt=broker, api_port=args.api_port,
                  mqtt_port=args.mqtt_port if not args.mqtt_url else 0, kafka_port=args.kafka_port,
                  mqtt_auth=args.auth, tied_to_parent=True, apart=True)
    other = stack.pid_file.running_up()
    if other is not None:
        sys.exit(f"mapservice up: another `mapservice up` (pid {other.pid}) runs on "
                 f"{stack.data_dir}; stop it (Ctrl-C there, or `kill {other.pid}`) or pass "
                 "another --data-dir")
    leftovers = stack.pid_file.leftovers()
    if leftovers:
        log.warning("the last `mapservice up` on this data dir ended without stopping its "
                    "components; ending them", components=[f"{p.name} (pid {p.pid})" for p in leftovers],
                    pid_file=str(stack.pid_file.path))
        lifetime.end(leftovers)
    stack.protect_data_dir()
    stack.start_guard()
    ros_map = load_ros_map(args.map)
    try:
        check_data_dir_map(stack.data_dir, ros_map)  # before the meta is published
        had_history = (stack.data_dir / "clickhouse").exists()
    except ValueError as exc:
        sys.exit(f"mapservice up: {exc}")
    try:
        if not had_history and args.robots and args.history_days > 0:
            # Its own process: chDB lets one process open a directory, and the engine is
            # released only when the process that opened it ends.
            done = subprocess.run([sys.executable, "-m", "mapservice.cli", "demo-history",
                                   "--data-dir", str(stack.data_dir), "--days", str(args.history_days),
                                   "--robots", str(args.robots), "--map", str(args.map)],
                                  preexec_fn=lifetime.die_with_parent)
            if done.returncode != 0:
                raise RuntimeError("writing the demo history failed (see above); "
                                   "`--history-days 0` starts without it")
        kafka_name = embedded_kafka_intro(stack, console)
        robot_credentials = None
        if args.auth:
            # Before the broker starts, which reads them then: a running Mosquitto would have
            # to be restarted to read them (Stack.reload_mqtt says why never by SIGHUP).
            with step(console, "giving each simulated robot its MQTT credential"):
                # The /controller page drives a robot too: it needs one to publish as.
                robot_credentials = stack.robot_credentials(
                    simulated_robot_ids(args) + [CONTROLLER_ROBOT])
        with step(console, f"starting Kafka ({kafka_name}) and the MQTT broker"):
            stack.start_brokers()
            stack.publish_meta(meta_for(ros_map))
        # Three processes, as the split deployment runs them: the history consumer never
        # shares a process (its CPU, memory, threads) with API reads and exports.
        with step(console, "starting the ClickHouse server, the processors (creating the "
                  "ClickHouse schema) and the API, each its own process"):
            stack.start_apart()
        with step(console, "starting the MQTT-to-Kafka gateway"):
            stack.start_gateway()
        with step(console, "publishing the map's chunks (fresh data dir only)"):
            uploaded = upload_map_if_fresh(stack.settings(), stack.data_dir, ros_map,
                                           SystemClock().now_ms(), had_history)
        if args.robots:
            # The shift simulator (robots on the map's free space, paths, batteries, pallets
            # and doors) unless the 2019 load test is asked for.
            stack.spawn("sim", "sim", "--robots", str(args.robots), "--map", str(args.map),
                        *(["--load-test"] if args.load_test else []),
                        *(["--credentials", str(robot_credentials)] if robot_credentials else []))
        rows: list[tuple[str, str]] = []  # the address table: (what, where)

        def row(name: str, value: str) -> None:
            rows.append((name, value))

        row("API", stack.api_url + "  (docs at /docs)")
        row("MQTT (robots)", stack.mqtt_url + (
            "  (robot identities: anonymous clients refused; add a robot with `mapservice robot "
            f"add <robotId> --data-dir {stack.data_dir}`)" if args.auth else "  (anonymous)"))
        if broker in ("mosquitto", "amqtt"):
            row("MQTT broker", f"Mosquitto, store in {stack.data_dir / 'mosquitto'}"
                if broker == "mosquitto" else "amqtt, no store (Mosquitto is not installed)")
        if robot_credentials:
            row("Robots' MQTT credentials", f"{robot_credentials} (the simulated robots' "
                f"and {CONTROLLER_ROBOT}'s: type its password on {stack.api_url}/controller)")
        row("MQTT WebSocket (browsers)", stack.mqtt_ws_url or "(none)")
        row(f"Kafka ({kafka_name})", f"127.0.0.1:{stack.kafka_port}  (" + kafka_keeps(stack) + ")")
        row("ClickHouse", f"{stack.clickhouse_url}  (`mapservice clickhouse-server` over "
            f"{Settings(data_dir=stack.data_dir).resolved_clickhouse_dsn}; user default, password "
            f"in {stack.data_dir / 'secrets' / 'clickhouse-password'})")
        row("Processors health", f"http://127.0.0.1:{stack.processors_health_port}/readyz")
        row("SQL (analysts, read-only)", f"{stack.api_url}/clickhouse  user analyst, password "
            f"in {stack.data_dir / 'secrets' / 'analyst-password'} (docs/analysts.md)")
        for name, where in api_token_rows(stack.settings()):
            row(name, where)
        row("Gateway health", f"http://127.0.0.1:{stack.health_port}/readyz")
        row("Map", f"{args.map} ({ros_map.width} x {ros_map.height} px; "
            + (f"{uploaded} chunks published)" if uploaded else "as stored)"))
        row("Simulated robots", f"{args.robots} on {args.map}"
            + (" (2019 load test)" if args.load_test else " (shift simulator)"))
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
    fetches the Apache Kafka jars first, with progress, when they are not cached yet."""
    from mapservice.local import kafka_broker

    if stack.kafka == "tansu":
        why = ("no Java runtime found (`make up` installs it as root)"
               if kafka_broker.java_binary() is None else "MAPSERVICE_EMBEDDED_KAFKA=tansu")
        console.print(f"[yellow]Kafka is tansu: {why}. {kafka_broker.TANSU_COST}; use Apache "
                      "Kafka for anything longer than a working session (README, embedded "
                      "mode).[/yellow]")
        return "tansu, in memory"
    version = kafka_broker.kafka_version()
    settings = stack.settings()
    jars = settings.kafka_jars_dir or kafka_broker.default_jars_dir()
    if not (jars / ".complete").exists():
        console.print(f"fetching Apache Kafka {version}'s jars with Maven into {jars} (once)...")
        kafka_broker.ensure_jars(jars, progress=lambda line: console.print(f"  {line}",
                                                                           highlight=False))
    return f"Apache Kafka {version}"


def kafka_keeps(stack) -> str:
    if stack.kafka == "tansu":
        return "no retention; a restart loses what it held"
    settings = stack.settings()
    return (f"log in {stack.data_dir / 'kafka'}, kept {settings.embedded_kafka_retention_hours} h "
            f"and at most {settings.embedded_kafka_retention_bytes // 1024**2} MB a partition")


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
            ("API writer token (robots)", "api_writer_tokens", WRITER_TOKEN_FILE,
             "REST writes; `mapservice robot` and `map upload` read it from there"),
            ("API admin token", "admin_token", ADMIN_TOKEN_FILE, "deletes, changing the map"),
            ("API operator token", "api_operator_tokens", OPERATOR_TOKEN_FILE,
             "editing points of interest and zones"),
            ("API reader token", "api_reader_tokens", READER_TOKEN_FILE, "reads")):
        if field == "api_reader_tokens" and settings.api_read_access == "open":
            continue
        where = (f"MAPSERVICE_{field.upper()}" if token_list(getattr(settings, field))
                 else str(secrets_dir(settings.data_dir) / file))
        rows.append((title, f"{where}  ({use}: 'Authorization: Bearer <token>')"))
    rows.append(("API reads", "open (MAPSERVICE_API_READ_ACCESS=open)"
                 if settings.api_read_access == "open" else "need a token"))
    return rows


def cmd_demo_history(args) -> None:
    """Days of the shift simulator, fast-forwarded into a data dir nothing else has open."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from mapservice.runtime.logs import configure
    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.local.up_output import PROGRESS_LOG_S, ProgressLog

    console = Console()
    # On a terminal a progress bar; else (a file, a pipe: the bar prints nothing there) a
    # log line every PROGRESS_LOG_S, so a logged first run shows it is getting on.
    configure("WARNING" if console.is_terminal else "INFO", "console", "demo-history")
    data_dir, days, robots = Path(args.data_dir), args.days, args.robots
    try:
        ros_map = load_ros_map(args.map)
    except (OSError, ValueError) as exc:
        sys.exit(f"mapservice demo-history: cannot read the map {args.map}: {exc}")
    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.adapters.clock import SystemClock
    from mapservice.local.demo_history import backfill

    settings = Settings(data_dir=data_dir)
    store = ClickHouseStore.from_settings(settings)
    try:
        store.migrate()
        if store.counts().poses:
            sys.exit(f"mapservice demo-history: {data_dir} already has history; it writes only "
                     "into a fresh data dir")
        what = f"simulating the last {days:g} days of {robots} robots"
        with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f} %"),
                      TimeElapsedColumn(), console=console, transient=True,
                      disable=not console.is_terminal) as bar:
            task = bar.add_task(what, total=1.0)
            logged = ProgressLog(what, PROGRESS_LOG_S)

            def progress(done: float) -> None:
                bar.update(task, completed=done)
                if not console.is_terminal:
                    logged.update(done)

            result = backfill(store, ros_map, days=days, robots=robots, now_ms=SystemClock().now_ms(),
                              conflict_window_ms=int(settings.conflict_window_s * 1000),
                              progress=progress)
    finally:
        store.close()
    console.print(f"wrote {days:g} days of demo history in {result.seconds:.0f} s: {result.poses:,} poses, "
                  f"{result.chunk_writes:,} map changes, {result.conflicts} conflicts")


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
        stack.is_alive, {name: (lambda n=name: stack.restart(n)) for name in list(stack.procs)},
        report=lambda message: console.print(f"[yellow]{message}; see {stack.log_dir}[/yellow]"),
        base_s=base_s)
    while True:
        supervisor.check()
        if stack.reload_mqtt_if_files_changed():
            console.print("robots' MQTT credentials changed: Mosquitto restarted to read them "
                          "(its queued messages kept)")
        time.sleep(0.5)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapservice", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    up = sub.add_parser("up", help="run everything on embedded defaults, with simulated robots")
    up.add_argument("--data-dir", default=".mapservice-data",
                    help="where ClickHouse data, broker data and logs live (resumed if present)")
    up.add_argument("--robots", type=int, default=5, help="simulated robots (0: none)")
    up.add_argument("--map", default=str(DEFAULT_MAP), help="ROS map YAML for the simulation")
    up.add_argument("--history-days", type=float, default=7.0,
                    help="on a fresh data dir, first write this many days of simulated history "
                         "(the shift simulator, fast-forwarded; about 11 s a day here); 0: none")
    up.add_argument("--load-test", action="store_true",
                    help="simulate the 2019 load test (circles, re-sent chunks) instead of a shift")
    up.add_argument("--mqtt-url", help="use this MQTT broker instead of the embedded one "
                    "(Mosquitto when installed, else amqtt)")
    up.add_argument("--auth", action="store_true",
                    help="authentication on, as in production: the embedded broker is Mosquitto "
                         "with a password file and ACL, each simulated robot gets its own MQTT "
                         "credential (DATA_DIR/secrets/robots.json), anonymous MQTT clients are "
                         "refused (REST writes always need a token)")
    up.add_argument("--api-port", type=int, default=8080, help="HTTP API and replay UI port")
    up.add_argument("--mqtt-port", type=int, default=1883, help="MQTT port for robots")
    up.add_argument("--kafka-port", type=int, default=0, help="0: a free port")
    up.add_argument("--restart-base-s", type=float, default=1.0, metavar="SECONDS",
                    help="first wait before restarting a component that exited; doubles on "
                         "each failure in a row, at most 60 s")
    up.add_argument("--open-browser", action="store_true",
                    help="open the replay UI in a browser once up")
    up.set_defaults(func=cmd_up)

    gw = sub.add_parser("gateway", help="MQTT-to-Kafka gateway (configured from MAPSERVICE_*)")
    gw.add_argument("--health-port", type=int, default=None,
                    help="serve /healthz, /readyz and /metrics on this port (default: none)")
    gw.set_defaults(func=cmd_gateway)

    pr = sub.add_parser("processors", help="stream processors: history sink (needs a ClickHouse server)")
    pr.add_argument("--health-port", type=int, default=None,
                    help="serve /healthz, /readyz and /metrics on this port (default: none)")
    pr.set_defaults(func=lambda a: cmd_serve(a, api=False, component="processors"))

    api = sub.add_parser("api", help="HTTP API only (needs a ClickHouse server)")
    api.set_defaults(func=lambda a: cmd_serve(a, processors=False, component="api"))

    demo = sub.add_parser("demo-history", help="write days of simulated shift history into a data "
                                               "dir (what `up` does on a fresh one)")
    demo.add_argument("--data-dir", default=".mapservice-data", help="the embedded data dir (not in use)")
    demo.add_argument("--days", type=float, default=7.0, help="how many days back from now")
    demo.add_argument("--robots", type=int, default=5, help="simulated robots (ids sim-000, ...)")
    demo.add_argument("--map", default=str(DEFAULT_MAP), help="ROS map YAML of the floor")
    demo.set_defaults(func=cmd_demo_history)

    mig = sub.add_parser("migrate", help="apply the ClickHouse schema migrations of this release "
                         "once (production runs it as a Job; components then find the schema)")
    mig.add_argument("--lock-timeout-s", type=float, default=600.0,
                     help="how long to wait for another running migration before giving up")
    mig.add_argument("--break-lock", action="store_true",
                     help="first drop a lock left by a migration that died (check none runs!)")
    mig.set_defaults(func=cmd_migrate)

    chs = sub.add_parser("clickhouse-server", help="the ClickHouse HTTP interface over the data "
                         "dir's chDB, for processes that run apart (the split deployment on one "
                         "machine); the one process that opens the directory")
    chs.add_argument("--host", default="127.0.0.1", help="address to listen on")
    chs.add_argument("--port", type=int, default=8123, help="port to listen on")
    chs.add_argument("--read-write", action="store_true",
                     help="let MAPSERVICE_CLICKHOUSE_USERNAME write (default: every user read-only)")
    chs.set_defaults(func=cmd_clickhouse_server)

    sql = sub.add_parser("sql", help="run one read-only SQL statement on the running service "
                         "(the analyst's ClickHouse HTTP endpoint) and print the result")
    sql.add_argument("query", help="the statement; - reads it from stdin")
    sql.add_argument("--url", default="http://127.0.0.1:8080/clickhouse",
                     help="the service's ClickHouse endpoint (the API's /clickhouse)")
    sql.add_argument("--format", default="PrettyCompact",
                     help="a ClickHouse output format: PrettyCompact, CSVWithNames, JSONEachRow, "
                          "Parquet, ... (a FORMAT clause in the query wins)")
    sql.add_argument("--user", default=None, help="default: MAPSERVICE_ANALYST_USERNAME (analyst)")
    sql.add_argument("--password", default=None,
                     help="default: MAPSERVICE_ANALYST_PASSWORD, else the one `up` generated in "
                          "the data dir")
    sql.add_argument("--data-dir", default=None,
                     help="where to find the generated password (default: MAPSERVICE_DATA_DIR)")
    sql.set_defaults(func=cmd_sql)

    export = sub.add_parser("export", help="download a time window from the running service: "
                            "the map and robots as MCAP (Foxglove, Lichtblick) or a table as "
                            "CSV/Parquet")
    export.add_argument("dataset", choices=["replay", "robot-poses", "chunk-changes",
                                            "chunk-conflicts", "dead-letters", "vehicle-states",
                                            "vehicle-errors", "vehicle-connections"],
                        help="replay: MCAP of map and robots (at most 24 h); else an analysts' "
                             "view (docs/analysts.md; at most 7 days); vehicle-*: the VDA 5050 "
                             "tables vda_states, vda_errors, vda_connections")
    export.add_argument("--from", dest="from_", required=True,
                        help="start, ISO 8601 (2026-11-23T08:00:00Z) or epoch ms")
    export.add_argument("--to", required=True, help="end (exclusive), ISO 8601 or epoch ms")
    export.add_argument("--format", choices=["csv", "parquet"], default="csv",
                        help="for tables (replay is always MCAP)")
    export.add_argument("--robot", default=None, help="only this robot (tables)")
    export.add_argument("--out", default=None, help="file to write (default: <dataset>.<ext>)")
    export.add_argument("--api", default="http://127.0.0.1:8080", help="the service's API")
    export.set_defaults(func=cmd_export)

    serve = sub.add_parser("serve", help="processors and API in one process (chdb needs this)")
    serve.set_defaults(func=cmd_serve)

    from mapservice.robot.cli import add_parsers as add_robot_parsers

    add_robot_parsers(sub)  # map, sim, robot, drive

    from mapservice.bench.cli import add_bench_parser

    add_bench_parser(sub)

    from mapservice.bench.history_loader import add_parser as add_load_history_parser

    add_load_history_parser(sub)

    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
