"""docs/analysts.md's incidents-per-cell query, run as the guide prints it on a chDB store:
it places every incident in the cell the API's incidents heatmap gives it
(`IncidentReader.incidents_per_cell`: the place rounded half to even to the millimetre,
floored to the cell), on the cells' edges and the roundings' ties as anywhere else."""

from __future__ import annotations

import random
import time
from collections import Counter
from pathlib import Path

from mapservice.core.incidents import Incident, PoseRef, incident_id
from tests.conftest import clone_migrated

GUIDE = Path(__file__).parents[4] / "docs" / "analysts.md"


def guide_query(database: str) -> str:
    """The guide's SQL block after "Incidents per cell come from", on `database`."""
    after = GUIDE.read_text().split("Incidents per cell come from", 1)[1]
    return after.split("```sql", 1)[1].split("```", 1)[0].replace("mapservice.", f"{database}.")


def incident(at_ms: int, x: float, y: float, robot: str) -> Incident:
    return Incident(
        incident_id=incident_id("near_miss", (robot,), at_ms),
        kind="near_miss",
        robots=(robot,),
        start_ms=at_ms,
        end_ms=at_ms + 1_000,
        ongoing=False,
        x=x,
        y=y,
        severity="warning",
        measure=0.5,
        evidence=(PoseRef(robot, at_ms, x, y),),
    )


def test_the_guides_incidents_per_cell_query_places_them_as_the_api(open_store, chdb_dir):
    store = open_store("clickhouse")
    clone_migrated(chdb_dir, store.database)
    store.migrate()
    now = int(time.time() * 1000) - 60_000  # inside the guide's last seven days
    rng = random.Random(5)
    # On the edges, a hair inside them and on the millimetre's ties, both signs; then anywhere.
    edges = [k * 0.5 + d for k in range(-4, 5) for d in (0.0, -0.0004, 0.0004, -0.0005, 0.0005)]
    places = [(x, rng.choice(edges)) for x in edges]
    places += [(rng.uniform(-30, 30), rng.uniform(-30, 30)) for _ in range(200)]
    rows = [incident(now - n * 1_000, x, y, f"r{n}") for n, (x, y) in enumerate(places)]
    store.append_incidents(rows, now)
    api = store.incidents_per_cell(now - 3_600_000, now + 3_600_000, 1, limit=10_000).cells
    guide: Counter[tuple[int, int]] = Counter()
    for i, j, _kind, n in store.connection.rows(guide_query(store.database), {}):
        guide[(int(i), int(j))] += int(n)
    assert sum(api.values()) == len(rows)
    assert dict(guide) == dict(api)
