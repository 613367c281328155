"""The data dir is private to its owner: it holds the secrets, the broker's store and
password file, the logs and the history."""

from __future__ import annotations

import os
from pathlib import Path


def protect_data_dir(data_dir: Path) -> None:
    """The data dir 0700 and nothing in it readable by others: also a data dir made by an
    older release, whose files were group and world readable."""
    data_dir.mkdir(parents=True, exist_ok=True)
    data_dir.chmod(0o700)
    for root, dirs, files in os.walk(data_dir):
        for name in dirs + files:
            path = Path(root, name)
            try:
                mode = path.lstat().st_mode
                if not path.is_symlink() and mode & 0o077:
                    path.chmod(mode & 0o7700)
            except FileNotFoundError:  # a scratch file of a running engine, gone since
                continue
