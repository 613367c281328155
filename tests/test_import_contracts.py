"""The architecture's import contracts (pyproject.toml, [tool.importlinter]) catch what they
are for: a circle, a product module importing the benchmarks or the local stack, I/O in the
core. `make lint` checks them on the checkout (`python -m tools.lint_imports`).

Each breaking module is written into a copy of the checkout's layout (its folders, each
module a symlink to its file), never into the checkout; the linter reads that copy with
`--source-root`, naming every module as installed (pyproject's package-dir mapping).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from tests.fixtures.paths import ROOT
from tools.installed_layout import modules


def stage(tmp: Path) -> Path:
    """The checkout's package folders under `tmp`, as real folders of symlinked modules."""
    for module in modules().values():
        target = tmp / module.relative_to(ROOT)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.symlink_to(module)
    return tmp


def lint_imports(staged: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tools.lint_imports", "--source-root", str(staged), "--no-cache"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def write(staged: Path, module: str, source: str) -> None:
    """A module under its installed name, in the staged folder that package is installed from."""
    package, name = module.rsplit(".", 1)
    package_init = modules(staged)[package]
    (package_init.parent / f"{name}.py").write_text(
        f'"""A module that breaks a contract."""\n{source}'
    )


def broken(result: subprocess.CompletedProcess[str], contract: str, module: str) -> bool:
    """The contract is reported broken, and the report names the module that breaks it (in
    full, or relative to the package it reports on)."""
    report = result.stdout
    details = report.split("Broken contracts", 1)[-1]
    return f"{contract} BROKEN" in report and module.rsplit(".", 1)[1] in details


@pytest.fixture
def staged(tmp_path: Path) -> Path:
    return stage(tmp_path)


def test_the_stage_holds_every_component(staged: Path) -> None:
    """The installed names cover the mapped subpackages, so the contracts see the whole
    service, and the staged copy holds each of their files where the checkout does."""
    installed = modules(staged)
    for module, path in (
        ("mapservice.api.app", "api/app.py"),
        ("mapservice.processors.app", "processors/app.py"),
        ("mapservice.ingest.gateway", "ingest/gateway.py"),
        ("mapservice.robot.sim", "robot/sim.py"),
        ("mapservice.core.events", "mapservice/core/events.py"),
    ):
        assert installed[module] == staged / path, module
        assert installed[module].is_file(), module
    assert set(installed) == set(modules())


def test_an_import_circle_breaks_the_contracts(staged: Path) -> None:
    """Two processors modules importing each other (even for type hints only) are refused."""
    write(staged, "mapservice.processors.circle_a", "from mapservice.processors import circle_b\n")
    write(
        staged,
        "mapservice.processors.circle_b",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from mapservice.processors import circle_a\n",
    )
    result = lint_imports(staged)
    assert result.returncode == 1, result.stdout + result.stderr
    assert broken(
        result, "No import circles between modules or packages", "mapservice.processors.circle_a"
    )


def test_a_product_module_importing_the_benchmarks_breaks_the_contracts(staged: Path) -> None:
    """An API module that imports a benchmark breaks the product/tooling boundary and the layers."""
    write(staged, "mapservice.api.uses_bench", "from mapservice.bench import ingest\n")
    result = lint_imports(staged)
    assert result.returncode == 1, result.stdout + result.stderr
    assert broken(
        result,
        "The product never imports the local stack, the benchmarks or the test twins",
        "mapservice.api.uses_bench",
    )
    assert broken(
        result, "Layers: each part imports only what is below it", "mapservice.api.uses_bench"
    )


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
    assert result.returncode == 1, result.stdout + result.stderr
    assert broken(result, "Layers: each part imports only what is below it", importer)
    if importer.startswith("mapservice.processors"):
        assert broken(
            result,
            "The product never imports the local stack, the benchmarks or the test twins",
            importer,
        )


def test_io_in_the_core_breaks_the_contracts(staged: Path) -> None:
    """A core module that opens files or imports an adapter is refused."""
    write(
        staged,
        "mapservice.core.reads_files",
        "from pathlib import Path\nfrom mapservice.adapters import clock\n",
    )
    result = lint_imports(staged)
    assert result.returncode == 1, result.stdout + result.stderr
    assert broken(
        result,
        "The core performs no I/O: no network, process, file or broker libraries",
        "mapservice.core.reads_files",
    )
    assert broken(
        result, "Layers: each part imports only what is below it", "mapservice.core.reads_files"
    )


def test_every_module_says_its_job() -> None:
    """Every module of the installed tree opens with a docstring."""
    missing = [
        name
        for name, path in sorted(modules().items())
        if not ast.get_docstring(ast.parse(path.read_text()))
    ]
    assert not missing, f"modules without a docstring: {missing}"
