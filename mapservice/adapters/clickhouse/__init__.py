"""ClickHouse: the history store (one adapter per role over one `connection`, built by
`store.clickhouse_roles`: `migrations`, `writes`, `snapshots`, `reads`, `legacy`, `admin`,
...; `store.ClickHouseStore` is every role at once, for tests and tools), its
numbered migrations (`schema`; the pose tables' re-layouts in `pose_schema`), their cluster
rewrite (`cluster`) and what analysts see (`analyst_schema`, rendering `table_comments` and
`analyst_views`).
"""
