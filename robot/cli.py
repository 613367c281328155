"""The robot-side subcommands: `map`, `sim`, `robot`, `drive` (registered by mapservice.cli)."""

from __future__ import annotations

import json
import signal
import sys
import time

from mapservice.robot import DEFAULT_MAP

from .connection import add_mqtt_arguments


def _probability(text: str) -> float:
    import argparse

    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text} is not a probability between 0 and 1")
    return value


# --- map -----------------------------------------------------------------------------------


def cmd_map(args) -> None:
    from .chunks import describe, slice_to_dir, stitch_dir

    try:
        if args.map_command == "slice":
            meta = slice_to_dir(args.file, args.output_dir, args.chunk_width, args.chunk_height)
            print(
                f"{meta.chunk_rows * meta.chunk_cols} chunks ({meta.chunk_rows} rows x "
                f"{meta.chunk_cols} columns of {meta.chunk_width} x {meta.chunk_height} px) "
                f", meta.json and map.yaml in {args.output_dir}"
            )
        elif args.map_command == "upload":
            return _map_upload(args)
        elif args.map_command == "stitch":
            out = stitch_dir(
                args.working_dir, args.output, magic={"p2": "P2", "p5": "P5"}.get(args.format or "")
            )
            print(f"wrote {out}")
        else:
            print(json.dumps(describe(args.file, args.chunk_width, args.chunk_height), indent=2))
    except (OSError, ValueError, KeyError) as exc:
        sys.exit(f"mapservice map {args.map_command}: {exc}")


def _map_upload(args) -> None:
    """`map upload`: the whole map through the 2019 REST API, as events like any robot's."""
    import httpx
    from mapservice.robot.map_upload import MapSizeMismatch, upload_map_rest

    from mapservice.adapters.ros_map import load_ros_map

    from .api_client import admin_token, api_client, writer_token

    # Replacing the map is the admin's; uploading chunks is any writer's (a robot's).
    token = admin_token(args.admin_token) if args.replace else writer_token(args.token)
    if args.replace and not token:
        sys.exit(
            "mapservice map upload: --replace replaces the service's map for every robot; "
            "it is an admin operation: pass --admin-token (or MAPSERVICE_ADMIN_TOKEN)"
        )
    ros_map = load_ros_map(args.file)
    try:
        with api_client(args.api, token) as http:
            count = upload_map_rest(
                http,
                ros_map,
                time.time_ns() // 1_000_000,
                replace=args.replace,
                robot_id=args.robot_id,
            )
    except MapSizeMismatch as exc:
        sys.exit(f"mapservice map upload: {exc}")
    except httpx.HTTPError as exc:
        sys.exit(
            f"mapservice map upload: cannot upload to {args.api}: {exc}; is the service "
            "running (`make up`) and --api its address?"
        )
    print(
        f"uploaded {count} chunks of {args.file} ({ros_map.width} x {ros_map.height} px) "
        f"to {args.api} as robot {args.robot_id}"
    )


# --- sim -----------------------------------------------------------------------------------


def cmd_sim(args) -> None:
    import structlog

    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.runtime.startup import settings_for

    from .connection import robot_mqtt_from_args

    settings = settings_for("sim")
    log = structlog.get_logger("sim")
    mqtt_url = args.mqtt_url or settings.mqtt_url
    ros_map = load_ros_map(args.map)
    try:
        conn = robot_mqtt_from_args(args, mqtt_url, settings.mqtt_ca_file)
    except ValueError as exc:
        sys.exit(f"mapservice sim: {exc}")
    if args.load_test:
        return _load_test(args, mqtt_url, ros_map, log, conn)
    from rich.console import Console
    from rich.live import Live

    from .api_client import writer_token
    from .faults import Faults
    from .sim import SimConfig
    from .simrun import SimRunner, progress_table
    from .zone_feed import ZoneFeed

    # The operators' zones: read from the API (`up` names its own in the environment).
    feed = (
        None
        if args.no_zones
        else ZoneFeed(args.api or settings.public_base_url, writer_token(args.token))
    )
    try:
        runner = SimRunner(
            mqtt_url,
            ros_map,
            args.robots,
            seed=args.seed,
            prefix=args.prefix,
            faults=Faults(args.clock_skew, args.loss, args.bad_rate),
            config=SimConfig(change_every_s=args.change_every),
            mqtt_conn=conn,
            zone_feed=feed,
            zone_topic=settings.zone_advertisement_topic,
        )
    except ValueError as exc:
        sys.exit(f"mapservice sim: {exc}")
    signal.signal(signal.SIGTERM, lambda *_: runner.stop())
    console = Console()
    log.info("simulated robots starting", robots=args.robots, map=str(args.map), mqtt=mqtt_url)
    last = [0.0]

    def log_progress(r) -> None:
        now = time.monotonic()
        if now - last[0] >= 10:
            last[0] = now
            s = r.stats
            log.info(
                "simulating",
                robots=s.robots,
                poses=s.poses,
                chunks=s.chunks,
                bad=s.bad,
                lost=s.lost,
                errors=s.errors,
                map_changes=s.map_changes,
                rate_per_s=round(s.rate(), 1),
            )

    def run() -> None:
        if console.is_terminal and not args.quiet:
            with Live(progress_table(runner), console=console, refresh_per_second=2) as live:
                runner.run(args.seconds, on_tick=lambda r: live.update(progress_table(r)))
        else:
            runner.run(args.seconds, on_tick=log_progress)

    _until_stopped(run, runner.stop, mqtt_url)
    s = runner.stats
    log.info(
        "simulation stopped",
        robots=s.robots,
        poses=s.poses,
        chunks=s.chunks,
        bad=s.bad,
        lost=s.lost,
        errors=s.errors,
        map_changes=s.map_changes,
    )


def _load_test(args, mqtt_url, ros_map, log, conn) -> None:
    """The 2019 load test: one pose a second, the same chunks re-sent at new positions."""
    from mapservice.robot.loadgen import RobotFleet

    try:
        fleet = RobotFleet(mqtt_url, ros_map, args.robots, prefix=args.prefix, mqtt_conn=conn)
    except ValueError as exc:
        sys.exit(f"mapservice sim: {exc}")
    signal.signal(signal.SIGTERM, lambda *_: fleet.stop())
    started, last = time.monotonic(), [0.0]

    def progress(stats) -> None:
        now = time.monotonic()
        if now - last[0] >= 10:
            last[0] = now
            log.info(
                "simulating (load test)",
                robots=args.robots,
                poses=stats.poses,
                chunks=stats.chunks,
                rate_per_s=round((stats.poses + stats.chunks) / max(now - started, 1e-9), 1),
            )

    _until_stopped(lambda: fleet.run(args.seconds, on_tick=progress), fleet.stop, mqtt_url)


def _until_stopped(run, stop, mqtt_url: str) -> None:
    """Runs the robots until done or Ctrl-C; an unreachable broker ends with what to do."""
    try:
        run()
    except KeyboardInterrupt:
        stop()
    except PermissionError as exc:
        sys.exit(
            f"{exc}; check the credentials file (`mapservice robot add <robotId> --save FILE`)"
        )
    except OSError as exc:
        sys.exit(
            f"cannot reach the MQTT broker at {mqtt_url}: {exc}; "
            "start one (e.g. `make up`) or pass --mqtt-url"
        )


# --- robot, drive --------------------------------------------------------------------------


def cmd_robot(args) -> None:
    if args.robot_command is not None:
        return _robot_identity(args)
    if not args.map or not args.robot_id:
        sys.exit(
            "mapservice robot: the agent needs --map and --robot-id "
            "(or `mapservice robot add|remove|list` to manage robots' MQTT credentials)"
        )
    from .agent import main as agent_main

    agent_main(args)


def _broker_files(args):
    from pathlib import Path

    from pydantic import ValidationError

    from mapservice.adapters.mqtt_auth import AclTopics, BrokerFiles
    from mapservice.settings import Settings

    try:
        settings = Settings(**({"data_dir": Path(args.data_dir)} if args.data_dir else {}))
    except ValidationError as exc:
        sys.exit(
            f"mapservice robot {args.robot_command}: the MAPSERVICE_* settings do not load "
            f"({exc.errors()[0]['msg']}); they name the topics the ACL is about"
        )
    if args.emqx:
        from mapservice.adapters.emqx_users import EmqxUsers

        return settings, EmqxUsers(
            settings.emqx_api_url,
            settings.emqx_api_key,
            settings.emqx_api_secret.get_secret_value(),
            AclTopics.from_settings(settings),
        )
    embedded = BrokerFiles.in_data_dir(settings.data_dir, settings)
    files = BrokerFiles(
        Path(args.password_file) if args.password_file else embedded.password_file,
        Path(args.acl_file) if args.acl_file else embedded.acl_file,
        AclTopics.from_settings(settings),
    )
    return settings, files


def _where(files) -> str:
    if _is_emqx(files):
        return f"EMQX's built-in database ({files.api_url})"
    return f"{files.password_file} and {files.acl_file}"


def _is_emqx(files) -> bool:
    return not hasattr(files, "password_file")


def _reload_local_mosquitto(files) -> str:
    """How the change reaches the broker. Never a SIGHUP: Mosquitto 2.0.11 that started from
    its store and then got SIGHUP (with an ACL) no longer delivers to the persistent sessions
    it restored (the gateway's), losing what robots publish meanwhile; a restart keeps them."""
    if _is_emqx(files):
        return (
            "EMQX checks it at the robot's next connect (a connected client stays "
            "connected: kick it from the dashboard's Clients page)"
        )
    if (files.password_file.parent.parent / "up.pids.json").exists():
        return (
            "the running `mapservice up` restarts its Mosquitto within a second or two to "
            "read them (queued messages are kept; clients reconnect)"
        )
    return (
        "Mosquitto reads them when it starts: restart a running one (compose: `docker "
        "compose restart mosquitto`; not SIGHUP, which on Mosquitto 2.0.11 can stop "
        "delivery to the gateway's persistent session)"
    )


def _robot_identity(args) -> None:
    """`robot add|remove|list`: the broker's password file and ACL (or EMQX's built-in
    database with --emqx), one user per robot."""
    from mapservice.adapters.emqx_users import EmqxError
    from mapservice.adapters.mqtt_auth import is_master_control

    try:
        settings, files = _broker_files(args)
        if args.robot_command == "list":
            legacy = set(files.legacy_robots())
            for robot in files.robots():
                print(
                    robot
                    + (
                        "  (may also use the 2019 chunk topic)"
                        if robot in legacy
                        else "  (VDA 5050 master control)"
                        if is_master_control(robot)
                        else ""
                    )
                )
            return
        if args.robot_command == "remove":
            if not files.remove_robot(args.robot_id_arg):
                sys.exit(
                    f"mapservice robot remove: no robot {args.robot_id_arg!r} in {_where(files)}"
                )
            print(
                f"removed robot {args.robot_id_arg} from {_where(files)}; "
                + _reload_local_mosquitto(files)
            )
            return
        cred = files.add_robot(
            args.robot_id_arg, legacy_chunks=args.legacy_chunks, rotate=args.rotate
        )
    except (OSError, ValueError, EmqxError) as exc:
        sys.exit(f"mapservice robot {args.robot_command}: {exc}")
    if args.save:
        from .connection import save_credential

        save_credential(args.save, cred.robot_id, cred.password)
    reload = _reload_local_mosquitto(files)
    broker = args.broker or settings.mqtt_url
    if args.json:
        print(
            json.dumps(
                {
                    "robotId": cred.robot_id,
                    "username": cred.username,
                    "password": cred.password,
                    "broker": broker,
                    "topics": cred.topics,
                    "legacyChunkTopic": cred.legacy_chunks,
                    "storedIn": _where(files),
                },
                indent=2,
            )
        )
        return
    if "masterControl" in cred.topics:
        print(f"""VDA 5050 master control {cred.username}: MQTT credential \
{"rotated" if args.rotate else "created"} (the password is shown only now)

  username   {cred.username}
  password   {cred.password}
  broker     {broker}

  It publishes {cred.topics["publishes"]} (to every vehicle)
  and reads    {cred.topics["reads"]}; anything else the broker refuses.

Written: {_where(files)}; {reload}.""")
        return
    if "publishes" in cred.topics:  # a VDA 5050 vehicle
        print(f"""VDA 5050 vehicle {cred.username} (robot {cred.topics["robotId"]}): MQTT credential \
{"rotated" if args.rotate else "created"} (the password is shown only now)

  username   {cred.username}
  password   {cred.password}
  broker     {broker}

  It publishes {cred.topics["publishes"]}
  and reads    {cred.topics["reads"]}; anything else the broker refuses, and a payload
  naming another manufacturer or serialNumber is a dead letter (robot_id_mismatch).

Written: {_where(files)}; {reload}.""")
        return
    legacy = files.topics.legacy_chunk_topic
    saved = (
        f"\nSaved to {args.save} (for mapservice sim/robot/drive --credentials)."
        if args.save
        else ""
    )
    print(
        f"""robot {cred.robot_id}: MQTT credential {"rotated" if args.rotate else "created"} \
(the password is shown only now; the broker keeps its hash)

  username   {cred.username}
  password   {cred.password}
  broker     {broker}{
            "   (TLS: give the robot the broker's CA certificate)"
            if broker.startswith("mqtts")
            else ""
        }

  The robot publishes, exactly as in 2019 but with this username and password:
    {cred.topics["pose"]:<32} its pose (listing 16), payload robotId "{cred.robot_id}"
    {cred.topics["chunks"]:<32} its chunks (listing 14 payload, robotId "{cred.robot_id}")
    {legacy:<32} {
            "allowed for this robot (--legacy-chunks): any robotId"
            if cred.legacy_chunks
            else "refused by the broker (use the topic above)"
        }
  and reads {cred.topics["advertisements"]}. Anything else the broker refuses; a payload
  whose robotId differs from the topic's is a dead letter (robot_id_mismatch).

Written: {_where(files)}; {reload}.{saved}"""
        + (
            ""
            if args.emqx
            else """
EMQX (Kubernetes): the same command with --emqx stores the user in EMQX's built-in database
  (MAPSERVICE_EMQX_API_URL, MAPSERVICE_EMQX_API_KEY, MAPSERVICE_EMQX_API_SECRET)."""
        )
    )


def cmd_drive(args) -> None:
    from .drive import main as drive_main

    drive_main(args)


TOKEN_HELP = (
    "the robot's writer token for the REST API, sent as 'Authorization: Bearer ...' "
    "(default: MAPSERVICE_API_TOKEN, else the one `mapservice up` generated in "
    "MAPSERVICE_DATA_DIR, .mapservice-data)"
)


def add_parsers(sub) -> None:
    m = sub.add_parser("map", help="slice a ROS map into 2019 chunks, stitch it back, describe it")
    msub = m.add_subparsers(dest="map_command", required=True)
    sl = msub.add_parser("slice", help="cut a map (ROS YAML or PGM) into chunk PGMs + meta.json")
    sl.add_argument("file", help="map YAML (or a bare P2/P5 PGM); relative paths are fine")
    sl.add_argument(
        "--output-dir",
        "-o",
        required=True,
        help="directory for the chunk PGMs (chunk_<row>_<col>.pgm), meta.json "
        "and map.yaml (PGM flavour and ROS settings, for stitch)",
    )
    sl.add_argument("--chunk-width", type=int, default=100, help="chunk width in pixels")
    sl.add_argument("--chunk-height", type=int, default=100, help="chunk height in pixels")
    st = msub.add_parser("stitch", help="put a sliced map back together (cropping the padding)")
    st.add_argument("working_dir", help="directory with meta.json and the chunks")
    st.add_argument("--output", "-o", required=True, help="a .pgm, or a .yaml (with its .pgm)")
    st.add_argument("--format", choices=["p2", "p5"], help="PGM flavour (default: as sliced)")
    up = msub.add_parser(
        "upload",
        help="publish a whole map (meta and every chunk) to a running "
        "service through its 2019 REST API, as the 2019 fillDB did",
    )
    up.add_argument("file", help="map YAML (or a bare P2/P5 PGM)")
    up.add_argument(
        "--api",
        default="http://127.0.0.1:8080",
        help="base URL of the service's REST API (default: `make up`'s)",
    )
    up.add_argument(
        "--robot-id", default="map-upload", help="robot id the uploaded chunks are attributed to"
    )
    up.add_argument(
        "--replace",
        action="store_true",
        help="replace a stored map of another size (admin; needs --admin-token)",
    )
    up.add_argument(
        "--admin-token",
        default=None,
        help="the service's MAPSERVICE_ADMIN_TOKEN, for --replace (default: from the "
        "environment, else the one `mapservice up` generated in "
        "MAPSERVICE_DATA_DIR)",
    )
    up.add_argument("--token", default=None, help=TOKEN_HELP)
    info = msub.add_parser("info", help="size, geometry, chunk grid and pixel classes of a map")
    info.add_argument("file", help="map YAML (or a bare P2/P5 PGM)")
    info.add_argument("--chunk-width", type=int, default=100, help="chunk width in pixels")
    info.add_argument("--chunk-height", type=int, default=100, help="chunk height in pixels")
    m.set_defaults(func=cmd_map)

    sim = sub.add_parser("sim", help="simulated robots on a real map, publishing over MQTT")
    sim.add_argument(
        "--robots",
        type=int,
        default=5,
        help="how many robots (fewer when the map has no room for them)",
    )
    sim.add_argument("--map", default=str(DEFAULT_MAP), help="ROS map YAML the robots drive on")
    sim.add_argument("--mqtt-url", default=None, help="MQTT broker (default: MAPSERVICE_MQTT_URL)")
    sim.add_argument("--seconds", type=float, default=None, help="stop after this long")
    sim.add_argument("--seed", type=int, default=7, help="random seed (same seed, same shift)")
    sim.add_argument("--prefix", default="sim", help="robot ids are <prefix>-000, ...")
    sim.add_argument(
        "--clock-skew",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="each robot's clock is off by a fixed amount within +-SECONDS",
    )
    sim.add_argument(
        "--loss", type=_probability, default=0.0, help="probability that a message is not sent"
    )
    sim.add_argument(
        "--bad-rate",
        type=_probability,
        default=0.0,
        help="probability that a message is replaced by invalid input",
    )
    sim.add_argument(
        "--change-every",
        type=float,
        default=20.0,
        metavar="SECONDS",
        help="mean time between map changes (pallets, doors); 0: none",
    )
    sim.add_argument(
        "--load-test",
        action="store_true",
        help="the 2019 load test instead: robots in circles, the same chunks "
        "re-sent at new positions every 5 s",
    )
    sim.add_argument("--quiet", action="store_true", help="log lines instead of a live table")
    sim.add_argument(
        "--api",
        default=None,
        help="the service's REST API, where robots read the operators' keep-out and "
        "speed zones (on start and after each zone advertisement) (default: "
        "MAPSERVICE_PUBLIC_BASE_URL, which `up` sets to its API)",
    )
    sim.add_argument("--token", default=None, help=TOKEN_HELP)
    sim.add_argument(
        "--no-zones",
        action="store_true",
        help="ignore the operators' zones: robots drive through keep-out zones "
        "at full speed (the 2019 behaviour)",
    )
    add_mqtt_arguments(sim, many=True)
    sim.set_defaults(func=cmd_sim)

    rb = sub.add_parser(
        "robot",
        help="a robot agent: keeps its local map in sync with the service; "
        "`robot add|remove|list`: robots' own MQTT credentials",
    )
    rb.add_argument(
        "--map", help="the robot's map YAML (its PGM is kept in sync); needed by the agent"
    )
    rb.add_argument(
        "--robot-id", help="this robot's id (1-64 of A-Z a-z 0-9 _ . : @ -); needed by the agent"
    )
    rb.add_argument("--api", default="http://127.0.0.1:8080", help="base URL of the 2019 REST API")
    rb.add_argument("--token", default=None, help=TOKEN_HELP)
    rb.add_argument("--mqtt", default="mqtt://127.0.0.1:1883", help="cloud MQTT broker")
    rb.add_argument(
        "--pose",
        choices=["sim", "odom"],
        default="sim",
        help="sim: a simulated drive on the map; odom: JSON odometry from --odom-topic",
    )
    rb.add_argument(
        "--odom-topic",
        default="robot/odom",
        help="local topic with nav_msgs/Odometry-like JSON (the 2019 ROS bridge)",
    )
    rb.add_argument(
        "--odom-mqtt", default=None, help="broker of the odometry topic (default --mqtt)"
    )
    rb.add_argument(
        "--threshold",
        type=float,
        default=0.0,
        help="publish a changed chunk when more than this fraction of it changed",
    )
    rb.add_argument("--period", type=float, default=1.0, help="seconds between pose/map checks")
    rb.add_argument("--chunk-width", type=int, default=100, help="chunk width in pixels")
    rb.add_argument("--chunk-height", type=int, default=100, help="chunk height in pixels")
    rb.add_argument("--seconds", type=float, default=None, help="stop after this long")
    add_mqtt_arguments(rb, many=False)
    rb.set_defaults(func=cmd_robot, robot_command=None)
    ids = rb.add_subparsers(
        dest="robot_command",
        metavar="{add,remove,list}",
        help="manage robots' MQTT credentials (Mosquitto password file and ACL, "
        "or EMQX's built-in database)",
    )
    for name, text in (
        (
            "add",
            "give a robot its own MQTT user (username = robotId) and print "
            "the credential and topics to configure on the robot",
        ),
        ("remove", "take a robot's MQTT user away (it can no longer connect)"),
        ("list", "the robots that have an MQTT user"),
    ):
        cmd = ids.add_parser(name, help=text, description=text)
        if name != "list":
            cmd.add_argument(
                "robot_id_arg",
                metavar="robotId",
                help="the robot's id, its MQTT username (1-64 of A-Z a-z 0-9 _ . : @ -); "
                "a VDA 5050 vehicle's is <manufacturer>/<serialNumber>, a VDA 5050 "
                "master control's mapservice-master-<name> (it may order every vehicle)",
            )
        cmd.add_argument(
            "--data-dir",
            default=None,
            help="data dir whose mqtt/passwd and mqtt/acl the local Mosquitto reads "
            "(default: MAPSERVICE_DATA_DIR, else .mapservice-data)",
        )
        cmd.add_argument(
            "--emqx",
            action="store_true",
            help="EMQX's built-in database through its REST API instead of "
            "Mosquitto's files (MAPSERVICE_EMQX_API_URL, _API_KEY, _API_SECRET)",
        )
        cmd.add_argument(
            "--password-file",
            default=None,
            help="a Mosquitto password_file elsewhere (e.g. infra/mosquitto/passwd); "
            "default: DATA_DIR/mqtt/passwd",
        )
        cmd.add_argument(
            "--acl-file",
            default=None,
            help="the Mosquitto acl_file that goes with it (rewritten); default: DATA_DIR/mqtt/acl",
        )
        if name == "add":
            cmd.add_argument(
                "--legacy-chunks",
                action="store_true",
                help="also allow the 2019 topic iot/chunks/create, which names no "
                "robot (this robot may then write chunks as any robotId); "
                "default: refused, the robot uses iot/chunks/create/<robotId>",
            )
            cmd.add_argument(
                "--rotate",
                action="store_true",
                help="the robot exists already: give it a new password (the old one stops working)",
            )
            cmd.add_argument(
                "--broker",
                default=None,
                help="the broker's address as robots reach it, for the printout "
                "(default: MAPSERVICE_MQTT_URL)",
            )
            cmd.add_argument(
                "--save",
                default=None,
                metavar="FILE",
                help="also store the password in this credentials file (JSON, mode "
                "0600) for `mapservice sim/robot/drive --credentials FILE`",
            )
            cmd.add_argument(
                "--json", action="store_true", help="print the credential as JSON (for scripts)"
            )
        cmd.set_defaults(func=cmd_robot, robot_command=name)

    dr = sub.add_parser("drive", help="drive one robot with the arrow keys and paint its chunk")
    dr.add_argument(
        "--map", default=str(DEFAULT_MAP), help="ROS map YAML; must have the service's map size"
    )
    dr.add_argument("--robot-id", default="driver", help="the driven robot's id")
    dr.add_argument("--mqtt", default="mqtt://127.0.0.1:1883", help="the service's MQTT broker")
    dr.add_argument(
        "--api",
        default="http://127.0.0.1:8080",
        help="the service's REST API, asked for its map size before driving",
    )
    dr.add_argument(
        "--token",
        default=None,
        help=TOKEN_HELP + "; only needed where reading "
        "needs a token (MAPSERVICE_API_READ_ACCESS=token)",
    )
    dr.add_argument(
        "--no-size-check",
        action="store_true",
        help="do not ask --api for the map size (a bare MQTT broker without the "
        "service); a map of another size then corrupts the service's map",
    )
    dr.add_argument(
        "--start",
        type=float,
        nargs=2,
        metavar=("X", "Y"),
        help="start position in metres (default: a free cell)",
    )
    dr.add_argument("--step", type=int, default=10, help="pixels per key press and per screen cell")
    add_mqtt_arguments(dr, many=False)
    dr.set_defaults(func=cmd_drive)
    from .zones_cli import add_parser as add_zones_parser

    add_zones_parser(sub)
