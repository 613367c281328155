"""Where a benchmark keeps its stack's data."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

DATA_DIR_HELP = (
    "where the run's data goes, kept afterwards to look into; "
    "default: a fresh temporary directory, removed when the benchmark ends"
)


@contextmanager
def bench_data_dir(given: str | Path | None, prefix: str) -> Iterator[Path]:
    """`given` (made if missing, and kept), or a fresh temporary directory that is removed
    when the benchmark ends, however it ends: one ingest run of 1,000 robots leaves about
    250 MB, and a series of runs would otherwise fill the temporary file system."""
    if given:
        path = Path(given)
        path.mkdir(parents=True, exist_ok=True)
        yield path
        return
    path = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)
