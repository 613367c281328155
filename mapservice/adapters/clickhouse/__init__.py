"""ClickHouse: the history store (`store.ClickHouseStore`), its numbered migrations
(`schema`), their cluster rewrite (`cluster`) and what analysts see (`analyst_schema`).
"""
