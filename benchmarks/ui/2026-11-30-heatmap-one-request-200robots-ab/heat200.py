"""The page's week heatmap reads (this tree's incident_reads_phase: its page's requests)
against an API on the 200-robot week at /tmp/w200 (loaded by `bench ui --reuse`); the
history's incidents are not found (the list reads an empty table)."""

import json
import os
import sys
import time
from pathlib import Path

from mapservice.bench.incident_reads import incident_reads_phase, plan_reads
from mapservice.bench.ui_setup import ApiProcess, migrate
from mapservice.bench.yardstick import yardstick_ms
from mapservice.settings import Settings

data = Path("/tmp/w200")
doc = json.loads((data / "loaded-bench_seek.json").read_text())
oldest = time.time_ns() // 1_000_000 - Settings().retention_ms + 60_000
plan = plan_reads(doc["start_ms"], doc["end_ms"], 20, 1, oldest)
out = {
    "yardstick_ms": yardstick_ms(),
    "loadavg_before": os.getloadavg(),
    "plan_week": plan.week,
    "tree": sys.argv[1],
}
migrate(data / "ch", "bench_seek")
with ApiProcess(data / "ch", "bench_seek", data / "logs" / "api-heat.log") as api:
    out["incident_reads"] = incident_reads_phase(api.url, plan)
Path(sys.argv[2]).write_text(json.dumps(out, indent=2))
r = out["incident_reads"]
print(
    sys.argv[1],
    {k: (v.get("p50_ms"), v.get("p95_ms")) for k, v in r.items() if k.startswith("heatmap")},
)
