"""`make lint` passes: ruff's rules and mypy (strict on mapservice/core/) as pyproject.toml
configures them, ESLint over the UI, and CI runs it before the tests."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

from tests.fixtures.paths import ROOT

BIN = Path(sys.executable).parent

# What `mypy --strict` turns on beyond the baseline (mypy 1.x/2.x); the core sets each one.
STRICT_FLAGS = {
    "disallow_any_generics",
    "disallow_subclassing_any",
    "disallow_untyped_calls",
    "disallow_untyped_defs",
    "disallow_incomplete_defs",
    "check_untyped_defs",
    "disallow_untyped_decorators",
    "warn_return_any",
    "no_implicit_reexport",
    "extra_checks",
}


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(BIN / args[0]), *args[1:]],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )


def test_ruff_finds_nothing():
    result = run("ruff", "check", "--no-cache", ".")
    assert result.returncode == 0, "ruff check . (make lint) found:\n" + result.stdout[-4000:]


def test_mypy_finds_nothing():
    result = run("mypy")
    assert result.returncode == 0, "mypy (make lint) found:\n" + result.stdout[-4000:]


def test_the_core_is_typed_strictly():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    core = [o for o in config["overrides"] if "mapservice.core.*" in o["module"]]
    assert len(core) == 1, "pyproject.toml has no mypy override for mapservice.core.*"
    assert {flag for flag in STRICT_FLAGS if core[0].get(flag) is True} == STRICT_FLAGS
    assert not core[0].get("disable_error_code"), "the core has no baseline: every error counts"


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
