"""A benchmark's data directory: a given one is kept, a temporary one removed."""

from __future__ import annotations

import pytest

from mapservice.bench.workdir import bench_data_dir


def test_a_temporary_directory_is_removed_even_when_the_benchmark_fails(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)  # re-read TMPDIR
    with pytest.raises(RuntimeError), bench_data_dir(None, "bench-x-") as data:
        assert data.parent == tmp_path and data.name.startswith("bench-x-")
        (data / "run-1").mkdir()
        (data / "run-1" / "part.bin").write_bytes(b"x" * 1024)
        raise RuntimeError("the run failed")
    assert not data.exists()
    assert list(tmp_path.iterdir()) == []


def test_a_given_directory_is_made_and_kept(tmp_path) -> None:
    given = tmp_path / "runs" / "today"
    with bench_data_dir(str(given), "bench-x-") as data:
        assert data == given and data.is_dir()
        (data / "kept").write_text("x")
    assert (given / "kept").read_text() == "x"


@pytest.mark.parametrize("bench", ["soak", "timetravel"])
def test_a_benchmark_failing_before_its_run_leaves_no_directory(
    bench: str, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A failure while setting up (a map that does not load, a store that does not open)
    removes the temporary directory as a failed run does."""
    import argparse
    import tempfile

    from mapservice.bench import soak, timetravel

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))

    def fail(*args, **kwargs):
        raise RuntimeError("setup failed")

    if bench == "soak":
        monkeypatch.setattr("mapservice.adapters.ros_map.load_ros_map", fail)
        with pytest.raises(RuntimeError, match="setup failed"):
            soak.run(argparse.Namespace(data_dir=None), console=None)
    else:
        monkeypatch.setattr("mapservice.adapters.clickhouse.store.ClickHouseStore", fail)
        with pytest.raises(RuntimeError, match="setup failed"):
            timetravel.main(argparse.Namespace(data_dir=None, clickhouse_dsn=None, database=None))
    assert list(tmp_path.iterdir()) == []
