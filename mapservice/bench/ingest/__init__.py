"""`mapservice bench ingest`: the 2019 load test through the whole pipeline, measured.

One run:

1. start the whole stack (tansu, the MQTT broker, processors + API, gateway) on a fresh
   data directory and publish the map meta, as `mapservice up` does;
2. warm up: one extra robot publishes for a few seconds and the run waits until its
   messages are queryable, so the timed run starts on a pipeline that is consuming;
3. `RobotFleet` publishes the 2019 workload (one pose a second and one chunk every five
   seconds per robot) for `--seconds`, recording each message's publish wall time;
4. meanwhile a thread polls the API (`/api/v1/poses`, `/api/v1/chunk-events`) about every
   100 ms and notes when each (kind, robot, ts_ms) is first returned, and another listens
   on the live WebSocket, which the API sends an event on (stamping `sent_ms`) once its
   insert returned; the earlier of the two is when the event was known queryable;
5. after the fleet stops it waits until everything is queryable (or 60 s), scans the
   whole run window through the API to count lost and duplicated events, and reads
   `/api/v1/stats`;
6. it stops the stack, merges the ClickHouse parts (OPTIMIZE FINAL) and reads their
   size on disk.

CPU per component is the CPU time (user + system, including child processes) each
process used while the fleet ran, divided by the fleet's wall time: 100 % is one core.
"""
