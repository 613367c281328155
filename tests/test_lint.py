"""`make lint` is the one lint entry: ruff's rules and format check, mypy (--strict, with a
counted list of modules not there yet) and the import contracts, as pyproject.toml configures
them. CI runs it once, before the tests; these tests check its configuration, not run it again."""

from __future__ import annotations

import ast
import importlib.util
import json
import subprocess
import tomllib
from pathlib import Path

from tests.fixtures.paths import ROOT
from tools.installed_layout import modules
from tools.typecheck import sources

# The modules not yet held to mypy --strict (the overrides that disable error codes) and the
# (module, error code) pairs they silence. The list may only shrink: lower these when a
# module is fixed.
MOST_LAX_MODULES = 101
MOST_SILENCED_CODES = 235


def mypy_config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]


def silenced() -> dict[str, set[str]]:
    codes: dict[str, set[str]] = {}
    for override in mypy_config()["overrides"]:
        for module in override["module"]:
            codes.setdefault(module, set()).update(override.get("disable_error_code", ()))
    return {module: kinds for module, kinds in codes.items() if kinds}


def test_make_lint_runs_every_check():
    """The one entry CI calls runs ruff, the format check, mypy and the import contracts,
    each over the installed package names."""
    commands = subprocess.run(
        ["make", "-n", "lint"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    for command in (
        ".venv/bin/ruff check .",
        ".venv/bin/ruff format --check .",
        ".venv/bin/python -m tools.typecheck",
        ".venv/bin/python -m tools.lint_imports --no-logo",
    ):
        assert command in commands, f"make lint does not run {command!r}: {commands}"


def test_mypy_names_each_module_as_the_program_imports_it():
    """Each file mypy checks has the name Python imports it by (through the editable
    install), so pyproject's per-module settings name the modules the program runs."""
    for source in sources():
        if source.module.startswith("mapservice"):
            spec = importlib.util.find_spec(source.module)
            assert spec is not None and spec.origin is not None, source.module
            assert Path(spec.origin).resolve() == (ROOT / str(source.path)).resolve()


def imported_by(module: str, path: Path) -> set[str]:
    """The modules `module` imports (`from a import b`: `a`, which holds `b`)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1]
            found.add(
                ".".join(base + [node.module] if node.level and node.module else base)
                if node.level
                else str(node.module)
            )
    return found


def test_every_product_import_reaches_a_checked_module():
    """Every import of a `mapservice` module names a module mypy checks: none is left
    unresolved (and so unchecked, as `ignore_missing_imports` would let it be)."""
    checked = {source.module for source in sources()}
    missing = {
        f"{module} imports {name}"
        for module, path in modules().items()
        for name in imported_by(module, path)
        if name.startswith("mapservice") and name not in checked
    }
    assert not missing, sorted(missing)


def test_the_core_is_typed_strictly():
    """--strict for the whole run; the core has no exception of any kind."""
    config = mypy_config()
    assert config.get("strict") is True, "pyproject.toml's [tool.mypy] is not strict"
    for override in config["overrides"]:
        if any(module.startswith("mapservice.core") for module in override["module"]):
            assert set(override) <= {"module", "ignore_missing_imports"}, override
            assert override.get("ignore_missing_imports") is not True, override


def test_the_strict_exceptions_only_shrink():
    """Each module the strict run excuses exists under its installed name, and neither the
    modules nor the error codes they silence grow in number."""
    excused = silenced()
    installed = set(modules())
    assert not set(excused) - installed, f"not installed modules: {set(excused) - installed}"
    assert len(excused) <= MOST_LAX_MODULES, f"{len(excused)} modules excused from --strict"
    pairs = sum(len(kinds) for kinds in excused.values())
    assert pairs <= MOST_SILENCED_CODES, f"{pairs} error codes silenced"


def test_ci_lints_before_it_tests():
    steps = [
        line.strip()
        for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if line.strip().startswith("make ")
    ]
    assert steps[:2] == ["make lint", "make test"]


def test_make_lint_runs_the_uis_linter_after_installing_it():
    """The UI's ESLint is part of `make lint`, which installs the UI's packages first."""
    makefile = (ROOT / "Makefile").read_text()
    target = makefile.split("\nlint:", 1)[1].split("\n\n", 1)[0]
    prerequisites, recipe = target.split("\n", 1)
    assert "$(UI)/node_modules/.installed" in prerequisites.split()
    assert "cd $(UI) && npm run --silent lint" in recipe
    scripts = json.loads((ROOT / "replay-ui" / "package.json").read_text())["scripts"]
    assert scripts["lint"] == "eslint ."
    assert (ROOT / "replay-ui" / "eslint.config.js").is_file()


# Written by tools, not by hand: the UI's API types are generated from the OpenAPI document.
GENERATED = {"replay-ui/src/lib/api-schema.d.ts"}
MAX_MODULE_LINES = 500


def test_no_hand_written_module_is_over_500_lines():
    listed = subprocess.run(
        ["git", "ls-files", "*.py", "*.ts", "*.vue", "*.js", "*.sh"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert len(listed) > 300, "git ls-files found too few modules: is this a git checkout?"
    over = {}
    for name in listed:
        path = ROOT / name
        if name in GENERATED or not path.is_file():
            continue
        lines = len(path.read_text(encoding="utf-8", errors="replace").splitlines())
        if lines > MAX_MODULE_LINES:
            over[name] = lines
    assert not over, f"split these by concern (at most {MAX_MODULE_LINES} lines): {over}"
