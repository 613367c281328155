"""The history store's CPU with the pose views fed every K batches (session 14, BENCHMARKS.md).

A chDB store (schema v10) takes one batch of ROBOTS x 0.11 poses every 110 ms, as the
history consumer's window makes them, for SECONDS seconds: `append_events` every batch,
`derive_views` of the batches since the last one every K batches. Prints the process's CPU
(chDB's merges included) per event, and the two calls' own shares. Run from the
repository with its venv, e.g.
`.venv/bin/python benchmarks/ingest/s14/pose_views_every_k_batches.py 9 30 5000`.
"""
import sys, tempfile, time, os
sys.path.insert(0, ".")
from tests.conftest import pose_event
from mapservice.adapters.clickhouse.store import ClickHouseStore
K = int(sys.argv[1]); SECONDS = float(sys.argv[2]); ROBOTS = int(sys.argv[3]) if len(sys.argv) > 3 else 5000
d = tempfile.mkdtemp()
s = ClickHouseStore(f"chdb://{d}")
getattr(s, "migrate", lambda: None)()
WINDOW = 0.11
per_batch = int(ROBOTS * WINDOW)
t0 = time.time(); c0 = time.process_time()
pending = []; n = 0; app = der = 0.0
start_ms = int(time.time() * 1000)
i = 0
while time.time() - t0 < SECONDS:
    tick = time.time()
    base = start_ms + int((tick - t0) * 1000)
    evs = [pose_event(f"r{(i*per_batch + j) % ROBOTS}", base + j % 100, x=j % 50, y=j % 40) for j in range(per_batch)]
    i += 1
    a = time.process_time(); s.append_events(evs); app += time.process_time() - a
    pending.extend(evs); n += 1
    if n % K == 0:
        a = time.process_time(); s.derive_views(pending); der += time.process_time() - a
        pending = []
    left = WINDOW - (time.time() - tick)
    if left > 0: time.sleep(left)
wall = time.time() - t0; cpu = time.process_time() - c0
print(f"K={K} batches={i} events={i*per_batch} wall={wall:.1f}s cpu={cpu:.2f}s ({100*cpu/wall:.0f}% of a core) "
      f"us/event total={1e6*cpu/(i*per_batch):.1f} append={1e6*app/(i*per_batch):.1f} derive={1e6*der/(i*per_batch):.1f}")
