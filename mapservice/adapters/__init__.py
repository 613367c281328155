"""Adapters: one module per outside thing, each behind a port of `mapservice.core.ports` where
the components depend on it. ClickHouse (`clickhouse/`, the history store and its schema),
Kafka (publisher, batch source, live publisher and relay, topics), MQTT clients, ROS map
files, exports (MCAP, CSV, Parquet), the clock, and in-memory twins for tests.
May import: `mapservice.core`, `mapservice.settings`, `mapservice.runtime`.
"""
