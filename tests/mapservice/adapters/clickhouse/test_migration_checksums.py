"""A migration, once released, never changes: a store that applied it refuses to migrate
when the code's checksum for it differs (test_migrations.py), and every other store would
silently run the new text. So the released migrations' checksums are written down here."""

from __future__ import annotations

from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION, checksums

RELEASED = {
    1: "9ac9a2b4ba502d0448152fe346aadcf90af21e47e22445334c5ce2837dbda66e",
    2: "6b223c19e237c0788607bf2e9f5962632f3276508ecafff36c1596bb16f7ba41",
    3: "92de0a2ac85649f944aa8b001e3a787ba89e9a2801066b7e1e1cde7e560fd4bc",
    4: "ec972a5222eaa34932bcb46eeddd9b6de0e8fc6e09756923959872d2d3e23de2",
    5: "57050731cfa8aa3c006de0183561bfa39ffc2596e8ecf73121001b8384ca66fc",
    6: "7d51e6af5d72969e3deee0b1bb46f1e7a96d956611db395f2d22e00fe81efe3f",
    7: "57bf754dab079c55403985d555abeb119a6f0761c79325b6fd0eaa1d16a42cf2",
    8: "234ce46803e6e589def598552870aee022fa186bc3bf7199fbff1b24cdb030d6",
    9: "9d7bed5c5fcf5c6ef4da059d767aee13ffbeab8e96efcb79e13ee76bb1bc743f",
    10: "783f95f80282d7007f05eb5e98c2a2cf25cffa82923320f272a0829129370d74",
    11: "9aa48fb9f701162643d2fb10f4f0355d40b0af696b1efb7ff655360eb259babc",
    12: "5d3ad07bf4436e6c3ae48072eb8e01df0877df066dcd5dcf1458a8169ffc48b6",
    13: "904712cc5932f6720188a6ba4d69e17a56897119a833d001b6af0d7c29bde88a",
    14: "b3e6fc6d9c08010fe85abf30788497b23ecc18e3e0f928a9e3b8343ab95aa2f9",
    15: "ced89524c1aea02c1db3ba5f7c939bfa1511b42fa1c33afd9df0ea5d613f6de4",
    16: "455f1d659c9e7d3c5b54eac781b737fd087147a93b95ab93c858866106467ffd",
    17: "98a18bc53345980883e0a31d50115ea713fd2b6420fa1a0f9d81fe5cd335f13b",
    18: "94fbfd3c199baf1bfd07a12319d171c36d8003b75f7a42e768895835322be81a",
    19: "712dbb185f1fc563ba5933fbfac543abb94423574ff42dfac007d677bd151777",
    20: "faecac90c16d2db036773724b7b959bf0704213f6236fb08e4f2404fbef8af76",
    21: "a3dfc52958ce913d70e9738723dcf58c63bfa11a94db2043e3906ed91cd3d919",
    22: "6251541a1b242007fe9baca1e18a54b0bfb29d7f1298b11ea79e6fb97624ee5c",
}


def test_released_migrations_keep_their_text():
    current = checksums()
    changed = sorted(v for v, h in RELEASED.items() if current.get(v) != h)
    assert not changed, (
        f"migrations {changed} changed after release: add a new migration instead of "
        "editing one that stores have applied"
    )


def test_every_migration_is_written_down_here():
    new = sorted(set(checksums()) - set(RELEASED))
    assert not new, (
        f"migrations {new} are new: once they are final, add their checksums "
        "(mapservice.adapters.clickhouse.schema.checksums()) to RELEASED"
    )
    assert max(RELEASED) == SCHEMA_VERSION
