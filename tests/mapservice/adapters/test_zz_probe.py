import tests.mapservice.adapters.test_store_retention as t
import pytest
orig = t._check
per = {}
def check(store, world, now, client):
    orig(store, world, now, client)
    store.optimize()
    day = (now - t.T0)//t.DAY
    per[day] = store.storage_bytes(); print("CARRIED", day, store._rows(f"SELECT count(), sum(rows), sum(bytes_on_disk) FROM system.parts WHERE database='{store.database}' AND table='carried_poses' AND active", {}), store._rows(f"SELECT count() FROM {store.database}.carried_poses", {}))
t._check = check
def test_probe(tmp_path):
    t.test_three_retention_periods_keep_the_floor_exact.__wrapped__ if False else None
    t.test_three_retention_periods_keep_the_floor_exact("clickhouse", tmp_path/"ch")
    for tbl in sorted(per[25]):
        print(tbl, per[9].get(tbl), per[17].get(tbl), per[25].get(tbl))
