"""The robot-side subcommands: `map`, `sim`, `robot`, `drive` (registered by mapservice.cli).

Their flags are here; what `map`, `sim` and `robot add|remove|list` do is in map_cli,
sim_cli and credentials_cli.
"""

from __future__ import annotations

import argparse
import sys

from mapservice.core.areas import DEFAULT_AREA_CHUNKS, DEFAULT_AREA_MARGIN_M
from mapservice.robot import DEFAULT_MAP

from .connection import add_mqtt_arguments
from .credentials_cli import cmd_credentials
from .map_cli import cmd_map
from .sim_cli import cmd_sim


def _probability(text: str) -> float:
    import argparse

    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text} is not a probability between 0 and 1")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not 1 or more")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"{text} is not 0 or more")
    return value


# --- robot, drive --------------------------------------------------------------------------


def cmd_robot(args: argparse.Namespace) -> None:
    if args.robot_command is not None:
        return cmd_credentials(args)
    if not args.map or not args.robot_id:
        sys.exit(
            "mapservice robot: the agent needs --map and --robot-id "
            "(or `mapservice robot add|remove|list` to manage robots' MQTT credentials)"
        )
    from .agent import main as agent_main

    agent_main(args)


def cmd_drive(args: argparse.Namespace) -> None:
    from .drive import main as drive_main

    drive_main(args)


TOKEN_HELP = (
    "the robot's writer token for the REST API, sent as 'Authorization: Bearer ...' "
    "(default: MAPSERVICE_API_TOKEN, else the one `mapservice up` generated in "
    "MAPSERVICE_DATA_DIR, .mapservice-data)"
)


def add_parsers(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
        "--no-incidents",
        action="store_true",
        help="no incidents on purpose (by default robots now and then stall on their route, "
        "drop off the network and charge late, a few of each an hour for five robots)",
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
    sim.add_argument(
        "--area-margin",
        type=_non_negative,
        default=DEFAULT_AREA_MARGIN_M,
        metavar="METRES",
        help="each robot reads the map changes of the advertisement areas within this "
        "distance of it (MAPSERVICE_ADVERTISEMENT_AREA_CHUNKS sets their size)",
    )
    sim.add_argument(
        "--no-advertisements",
        action="store_true",
        help="robots read no map changes (as the simulator did before advertisement areas)",
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
    rb.add_argument(
        "--advertisements",
        choices=["areas", "2019"],
        default="areas",
        help="areas: read the map changes of the advertisement areas around the robot; "
        "2019: every change of the plant on iot/chunks/advertisement",
    )
    rb.add_argument(
        "--area-chunks",
        type=_positive_int,
        default=DEFAULT_AREA_CHUNKS,
        help="side of an advertisement area in chunks: the service's "
        "MAPSERVICE_ADVERTISEMENT_AREA_CHUNKS",
    )
    rb.add_argument(
        "--area-margin",
        type=_non_negative,
        default=DEFAULT_AREA_MARGIN_M,
        metavar="METRES",
        help="read the areas within this distance of the robot",
    )
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
