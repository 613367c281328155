"""`mapservice zones import-mask`: a nav2 keep-out mask (map_server YAML and its image) made
into keep-out zones through the service's API, with the operator's token.

The API (POST /api/v1/annotations/import-mask) makes one zone per connected area of the
mask, with its holes, edges on pixel edges: exporting the keep-out mask afterwards gives
back the same pixels. A PGM is sent as a PNG (lossless, a tenth of the size): nav2's
warehouse mask in base64 is over the API's default body limit as a PGM.
"""

from __future__ import annotations

import argparse
import base64
import io
import os
import sys
from pathlib import Path
from typing import Any

import httpx
import yaml

from mapservice.runtime.secrets import OPERATOR_TOKEN_FILE, stored_secret

from .api_client import api_client, data_dir

OPERATOR_TOKEN_ENV = "MAPSERVICE_OPERATOR_TOKEN"


class MaskFiles(ValueError):
    """Mask files that cannot be read or sent; the message says what to fix."""


def operator_token(explicit: str | None = None) -> str | None:
    """--token, else MAPSERVICE_OPERATOR_TOKEN, else the one `mapservice up` generated."""
    return (
        explicit
        or os.environ.get(OPERATOR_TOKEN_ENV)
        or stored_secret(data_dir(), OPERATOR_TOKEN_FILE)
    )


def mask_files(path: Path) -> tuple[str, bytes]:
    """(the YAML's text, the image's bytes to send) of a mask given by its YAML, or by its
    image next to a YAML of the same name."""
    if path.suffix.lower() not in (".yaml", ".yml"):
        found = [p for p in (path.with_suffix(".yaml"), path.with_suffix(".yml")) if p.exists()]
        if not found:
            raise MaskFiles(
                f"{path} has no map_server YAML next to it ({path.with_suffix('.yaml').name}"
                "); pass the mask's YAML, which gives its resolution and origin"
            )
        path = found[0]
    try:
        text = path.read_text()
        doc = yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise MaskFiles(f"cannot read the mask YAML {path}: {str(exc)[:200]}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("image"), str):
        raise MaskFiles(f"{path} is no map_server YAML: it names no image (image: mask.pgm)")
    image_path = (
        Path(doc["image"]) if Path(doc["image"]).is_absolute() else path.parent / doc["image"]
    )
    try:
        image = image_path.read_bytes()
    except OSError as exc:
        raise MaskFiles(
            f"cannot read the mask image {image_path} that {path.name} names: {exc.strerror or exc}"
        ) from None
    return text, _as_png(image)


def _as_png(image: bytes) -> bytes:
    """An 8-bit PGM (maxval 255) as the same pixels in a PNG; anything else as it is (the
    API scales other PGM depths itself, and reads every image Pillow reads)."""
    from PIL import Image

    from mapservice.adapters.ros_map import read_pgm_header

    if image[:2] not in (b"P2", b"P5"):
        return image
    try:
        if read_pgm_header(image[:4096]).maxval != 255:
            return image
        out = io.BytesIO()
        with Image.open(io.BytesIO(image)) as img:
            img.convert("L").save(out, format="PNG", optimize=True)
        return out.getvalue()
    except Exception:  # noqa: BLE001 - the API says what is wrong with an unreadable image
        return image


def import_mask(http: httpx.Client, path: Path, name: str) -> dict[str, Any]:
    """Posts the mask; the API's answer ({"ids": [...], "at_ms": ...}). Raises MaskFiles
    for files it cannot send and httpx.HTTPStatusError for a refusal."""
    text, image = mask_files(path)
    response = http.post(
        "/api/v1/annotations/import-mask",
        json={"yaml": text, "image_base64": base64.b64encode(image).decode(), "name": name},
    )
    response.raise_for_status()
    imported: dict[str, Any] = response.json()
    return imported


def refusal(exc: httpx.HTTPStatusError) -> str:
    try:
        detail = exc.response.json().get("detail", exc.response.text)
    except ValueError:
        detail = exc.response.text
    hint = {
        401: "; pass the operator token with --token (or MAPSERVICE_OPERATOR_TOKEN)",
        403: "; the token is not an operator's: use one of MAPSERVICE_API_OPERATOR_TOKENS",
        413: "; the mask is over the API's body limit (MAPSERVICE_API_MAX_BODY_BYTES)",
    }
    return f"the service refused the mask ({exc.response.status_code}): {detail}" + hint.get(
        exc.response.status_code, ""
    )


def cmd_zones(args: argparse.Namespace) -> None:
    token = operator_token(args.token)
    try:
        with api_client(args.api, token, timeout=120) as http:
            answer = import_mask(http, Path(args.mask), args.name)
    except MaskFiles as exc:
        sys.exit(f"mapservice zones import-mask: {exc}")
    except httpx.HTTPStatusError as exc:
        sys.exit(f"mapservice zones import-mask: {refusal(exc)}")
    except httpx.HTTPError as exc:
        sys.exit(
            f"mapservice zones import-mask: cannot reach the API at {args.api}: {exc}; is the "
            "service running (`make up`) and --api its address?"
        )
    ids = answer["ids"]
    print(
        f"imported {args.mask} as {len(ids)} keep-out zone{'s' if len(ids) != 1 else ''} "
        f"named after {args.name!r}: {', '.join(ids[:10])}{' ...' if len(ids) > 10 else ''}"
    )


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    zones = sub.add_parser("zones", help="operators' zones on the floor (keep-out, speed limits)")
    zsub = zones.add_subparsers(dest="zones_command", required=True)
    imp = zsub.add_parser(
        "import-mask",
        help="make a nav2 keep-out mask (map_server YAML + PGM/PNG) into keep-out "
        "zones, one per connected area; the mask must lie exactly over the service's map",
        description="Posts the mask to POST /api/v1/annotations/import-mask with an operator "
        "token. Exporting the keep-out mask afterwards (GET /api/v1/costmap-filters/"
        "keepout/mask.pgm) gives back the same pixels.",
    )
    imp.add_argument(
        "mask", help="the mask's map_server YAML (or its image, next to a YAML of the same name)"
    )
    imp.add_argument(
        "--name",
        default="imported keep-out",
        help="the zones' name, numbered where the mask has several areas (default: "
        "'imported keep-out')",
    )
    imp.add_argument(
        "--api",
        default="http://127.0.0.1:8080",
        help="base URL of the service's REST API (default: `make up`'s)",
    )
    imp.add_argument(
        "--token",
        default=None,
        help="an operator token (default: MAPSERVICE_OPERATOR_TOKEN, else the one "
        "`mapservice up` generated in MAPSERVICE_DATA_DIR, .mapservice-data)",
    )
    zones.set_defaults(func=cmd_zones)
