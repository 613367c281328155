"""ClickHouse: the history store (`store.ClickHouseStore`, composed of one mixin per concern
over `connection`: `migrations`, `writes`, `snapshots`, `reads`, `legacy`, `admin`), its
numbered migrations (`schema`; the pose tables' re-layouts in `pose_schema`), their cluster
rewrite (`cluster`) and what analysts see (`analyst_schema`, rendering `table_comments` and
`analyst_views`).
"""
