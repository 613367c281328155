"""`mapservice map`: slice a ROS map into 2019 chunks, stitch it back, describe it, upload it."""

from __future__ import annotations

import argparse
import json
import sys
import time


def cmd_map(args: argparse.Namespace) -> None:
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


def _map_upload(args: argparse.Namespace) -> None:
    """`map upload`: the whole map through the 2019 REST API, as events like any robot's."""
    import httpx

    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.robot.map_upload import MapSizeMismatch, UploadRefused, upload_map_rest

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
    except UploadRefused as exc:
        sys.exit(f"mapservice map upload: the service refused the map: {exc}")
    except httpx.HTTPError as exc:
        sys.exit(
            f"mapservice map upload: cannot upload to {args.api}: {exc}; is the service "
            "running (`make up`) and --api its address?"
        )
    print(
        f"uploaded {count} chunks of {args.file} ({ros_map.width} x {ros_map.height} px) "
        f"to {args.api} as robot {args.robot_id}"
    )
