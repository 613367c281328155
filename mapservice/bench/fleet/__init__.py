"""The load fleets the benchmarks drive (`bench ingest`): RawFleet's worker processes
writing pre-encoded MQTT packets, and the packet encoder they share with the VDA 5050 fleet.
Tooling: the product never imports it."""
