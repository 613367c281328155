"""Maps for the robot tests (the repository's and, when present, every map in ../shared/maps)
and a real Mosquitto."""

from __future__ import annotations

from pathlib import Path

from tests.fixtures.mosquitto import mosquitto, mosquitto_identities  # noqa: F401 (fixtures)
from tests.fixtures.paths import MAPS, ROOT

SHARED_MAPS = ROOT.parent / "shared" / "maps"


def all_map_yamls() -> list[Path]:
    """Every ROS map YAML we have, each name once (shared/ wins: it has the keep-out mask)."""
    found: dict[str, Path] = {p.name: p for p in sorted(MAPS.glob("*.yaml"))}
    if SHARED_MAPS.is_dir():
        found.update({p.name: p for p in sorted(SHARED_MAPS.glob("*.yaml"))})
    return [found[k] for k in sorted(found)]
