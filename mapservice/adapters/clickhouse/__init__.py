"""ClickHouse: the history store (`store.ClickHouseStore`, composed of one mixin per concern
over `connection`: `migrations`, `writes`, `snapshots`, `reads`, `legacy`, `admin`), its
numbered migrations (`schema`), their cluster rewrite (`cluster`) and what analysts see
(`analyst_schema`).
"""
