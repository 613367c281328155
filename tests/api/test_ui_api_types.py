"""The replay UI's API types are generated from the API's OpenAPI document
(replay-ui/src/lib/api-schema.d.ts, `make api-types`): regenerated from the current routes,
they are what is committed, so a change to a route's shapes reaches the UI's type check."""

from __future__ import annotations

import difflib
import json
import shlex
import subprocess
import sys

import pytest

from tests.fixtures.paths import ROOT

UI = ROOT / "replay-ui"
GENERATED = UI / "src" / "lib" / "api-schema.d.ts"


def generator_argv(output: str) -> list[str]:
    """The package's `api-types` script (the one `make api-types` runs), writing to `output`."""
    script = shlex.split(json.loads((UI / "package.json").read_text())["scripts"]["api-types"])
    assert script[0] == "openapi-typescript" and "--output" in script, script
    script[script.index("--output") + 1] = output
    return [str(UI / "node_modules" / ".bin" / script[0]), *script[1:]]


def test_the_uis_api_types_are_generated_from_the_current_openapi_document(tmp_path) -> None:
    """Regenerating the types from the app's document gives the committed file, byte for byte."""
    if not (UI / "node_modules" / ".bin" / "openapi-typescript").exists():
        pytest.fail("replay-ui's packages are not installed: `make ui` (npm ci) installs them")
    document = subprocess.run(
        [sys.executable, "-m", "mapservice.api.openapi_document"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert document.returncode == 0, document.stderr[-2000:]
    out = tmp_path / "api-schema.d.ts"
    done = subprocess.run(
        generator_argv(str(out)),
        input=document.stdout,
        cwd=UI,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    fresh, committed = out.read_text(), GENERATED.read_text()
    diff = "".join(
        difflib.unified_diff(
            committed.splitlines(True), fresh.splitlines(True), "committed", "generated", n=1
        )
    )
    assert fresh == committed, (
        "replay-ui/src/lib/api-schema.d.ts is out of date with the "
        "API's routes: run `make api-types` and commit it\n" + diff[:3000]
    )


def test_the_document_is_the_same_whatever_the_environment_says() -> None:
    """Built from the settings' defaults: an environment that changes what the running API
    documents (reads behind a token) does not change the generated types."""

    def document(env: dict[str, str]) -> str:
        done = subprocess.run(
            [sys.executable, "-m", "mapservice.api.openapi_document"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            env={**env, "PATH": "/usr/bin:/bin"},
        )
        assert done.returncode == 0, done.stderr[-2000:]
        return done.stdout

    assert document({"MAPSERVICE_API_READ_ACCESS": "token"}) == document({})
