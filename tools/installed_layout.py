"""Where each module of the installed `mapservice` package lives in the checkout.

setuptools installs `ingest/`, `processors/`, `api/` and `robot/` as subpackages of
`mapservice` (pyproject's `[tool.setuptools] package-dir`), through an import hook in the
editable install. Static tools cannot run an import hook, so they are told the installed
name of every file from the same mapping setuptools reads.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = ROOT / "pyproject.toml"


def package_dirs(source_root: Path = ROOT) -> dict[str, Path]:
    """Each mapped package's installed name and its folder under `source_root`."""
    mapping = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-dir"]
    return {package: source_root / folder for package, folder in mapping.items()}


def modules(source_root: Path = ROOT) -> dict[str, Path]:
    """Every module of the installed packages by its installed name, in packages only
    (folders with an `__init__.py`, as setuptools installs them)."""
    found: dict[str, Path] = {}
    for package, folder in package_dirs(source_root).items():
        for path in sorted(folder.rglob("*.py")):
            relative = path.relative_to(folder)
            if not all(
                (folder / part).joinpath("__init__.py").is_file() for part in _parents(relative)
            ):
                continue
            parts = relative.with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join((package, *parts))] = path
    return found


def _parents(relative: Path) -> list[Path]:
    return [Path(*relative.parts[:depth]) for depth in range(len(relative.parts))]
