"""The architecture's import contracts (pyproject.toml, [tool.importlinter]) hold, and each
one fails when a change breaks it: a circle, a product module importing the benchmarks or
the local stack, I/O in the core.

import-linter (grimp) finds a package's modules by walking its one directory, but setuptools
installs `ingest/`, `processors/`, `api/` and `robot/` as `mapservice.*` subpackages from
folders beside `mapservice/`. So each check runs on a staged tree laid out as installed:
real directories, each module a symlink to its file in the checkout (pyproject's
package-dir mapping says where). Extra modules written into the stage show that a broken
contract is caught without touching the checkout.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from tests.fixtures.paths import ROOT

PYPROJECT = ROOT / "pyproject.toml"
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"


def stage(tmp: Path) -> Path:
    """The installed layout of every mapped package under `tmp`, as symlinks to the checkout."""
    package_dirs = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-dir"]
    for package, folder in package_dirs.items():
        source = ROOT / folder
        for module in source.rglob("*.py"):
            target = tmp / package.replace(".", "/") / module.relative_to(source)
            target.parent.mkdir(parents=True, exist_ok=True)
            if not target.exists():
                target.symlink_to(module)
    return tmp


def lint_imports(staged: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(staged)}
    return subprocess.run(
        [str(LINT_IMPORTS), "--config", str(PYPROJECT), "--no-cache"],
        cwd=staged,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def write(staged: Path, module: str, source: str) -> None:
    (staged / (module.replace(".", "/") + ".py")).write_text(source)


@pytest.fixture
def staged(tmp_path: Path) -> Path:
    return stage(tmp_path)


def test_every_import_contract_holds(staged: Path) -> None:
    """lint-imports keeps all four contracts on the checkout as it is."""
    result = lint_imports(staged)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "4 kept, 0 broken" in result.stdout


def test_the_stage_holds_every_component(staged: Path) -> None:
    """The staged tree has the mapped subpackages, so the contracts see the whole service."""
    for module in (
        "mapservice/api/app.py",
        "mapservice/processors/app.py",
        "mapservice/ingest/gateway.py",
        "mapservice/robot/sim.py",
        "mapservice/core/events.py",
    ):
        assert (staged / module).is_file(), module


def test_an_import_circle_breaks_the_contracts(staged: Path) -> None:
    """Two processors modules importing each other (even for type hints only) are refused."""
    write(staged, "mapservice.processors.circle_a", "from mapservice.processors import circle_b\n")
    write(
        staged,
        "mapservice.processors.circle_b",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from mapservice.processors import circle_a\n",
    )
    result = lint_imports(staged)
    assert result.returncode == 1
    assert "No import circles between modules or packages BROKEN" in result.stdout


def test_a_product_module_importing_the_benchmarks_breaks_the_contracts(staged: Path) -> None:
    """An API module that imports a benchmark breaks the product/tooling boundary and the layers."""
    write(staged, "mapservice.api.uses_bench", "from mapservice.bench import ingest\n")
    result = lint_imports(staged)
    assert result.returncode == 1
    assert (
        "The product never imports the local stack, the benchmarks or the test twins BROKEN"
        in result.stdout
    )
    assert "Layers: each part imports only what is below it BROKEN" in result.stdout


@pytest.mark.parametrize(
    "importer", ["mapservice.processors.uses_twin", "mapservice.local.uses_twin"]
)
def test_the_product_or_the_local_stack_importing_a_test_twin_breaks_the_contracts(
    staged: Path, importer: str
) -> None:
    """The memory twins stand in for adapters only in tests and benchmarks: a processors
    module (the product) or the local stack (`up`) that imports one is refused."""
    write(staged, importer, "from mapservice.testing import memory_store\n")
    result = lint_imports(staged)
    assert result.returncode == 1
    assert "Layers: each part imports only what is below it BROKEN" in result.stdout
    if importer.startswith("mapservice.processors"):
        assert (
            "The product never imports the local stack, the benchmarks or the test twins BROKEN"
            in result.stdout
        )


def test_io_in_the_core_breaks_the_contracts(staged: Path) -> None:
    """A core module that opens files or imports an adapter is refused."""
    write(
        staged,
        "mapservice.core.reads_files",
        "from pathlib import Path\nfrom mapservice.adapters import clock\n",
    )
    result = lint_imports(staged)
    assert result.returncode == 1
    assert (
        "The core performs no I/O: no network, process, file or broker libraries BROKEN"
        in result.stdout
    )
    assert "Layers: each part imports only what is below it BROKEN" in result.stdout


def test_every_module_says_its_job(staged: Path) -> None:
    """Every module of the installed tree opens with a docstring."""
    import ast

    missing = [
        str(module.relative_to(staged))
        for module in sorted(staged.rglob("*.py"))
        if not ast.get_docstring(ast.parse(module.read_text()))
    ]
    assert not missing, f"modules without a docstring: {missing}"
