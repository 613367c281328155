"""`mapservice robot add|remove|list`: robots' own MQTT credentials, in the broker's password
file and ACL (or EMQX's built-in database with --emqx)."""

from __future__ import annotations

import json
import sys


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
    return f"{files.password_file}, {files.acl_file} and {files.dynsec_file}"


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


def cmd_credentials(args) -> None:
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
  and reads {cred.topics["advertisements"]} (every change of the map) or the areas around
  it, {cred.topics["areaAdvertisements"]}. Anything else the broker refuses; a payload
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
