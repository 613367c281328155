"""The deployment files in infra/ agree with the code they deploy.

No Docker engine or Kubernetes cluster is at hand where these tests run, so they check
the files statically against the code itself: the settings object, the CLI's parser,
the real health handlers, the topics the service creates. Two checks use a local tool
when it is installed (mosquitto for the broker config, kubectl for kustomize).

This file: the files themselves, what they name (settings, CLI commands, secrets),
compose's consistency and the Dockerfile. test_manifest_components.py: each component
as deployed; test_mosquitto_conf.py: the shipped broker config.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
import tomllib

import pytest
import yaml

from tests.fixtures.paths import ROOT
from tests.infra.manifests import (
    COMPONENTS,
    COMPOSE,
    DOCKERFILE,
    DOCKERIGNORE,
    INFRA,
    INFRA_README,
    K8S,
    KUSTOMIZATION,
    MOSQUITTO_CONF,
    ONE_SHOT,
    SECRET_REF,
    SECRET_VARS,
    SETTINGS_VARS,
    STRIMZI_TOPICS,
    VAR_NAME,
    compose,
    compose_components,
    compose_env,
    compose_mapservice,
    container_argv,
    health_port,
    is_secret_name,
    jobs,
    k8s_docs,
    kustomize_resources,
    load_all,
    secret_keys_from_readme,
    workloads,
    yaml_files,
)


def test_every_yaml_file_in_infra_parses():
    """Every YAML file in infra/ parses (all its documents), and the deployment files exist."""
    for path in (
        COMPOSE,
        DOCKERFILE,
        MOSQUITTO_CONF,
        INFRA_README,
        KUSTOMIZATION,
        STRIMZI_TOPICS,
        DOCKERIGNORE,
    ):
        assert path.is_file(), f"missing {path.relative_to(ROOT)}"
    files = yaml_files()
    assert len(files) >= 5
    for path in files:
        docs = load_all(path)
        assert docs, f"{path.relative_to(ROOT)} has no YAML document"
        assert all(isinstance(doc, dict) for doc in docs), path
    for path in K8S.glob("*.yaml"):
        if path != KUSTOMIZATION:
            for doc in load_all(path):
                assert {"apiVersion", "kind", "metadata"} <= doc.keys(), path


def test_kustomization_lists_every_manifest_but_the_strimzi_topics():
    """kustomization.yaml lists every k8s manifest that exists, except strimzi-topics.yaml."""
    listed = kustomize_resources()
    on_disk = {p.name for p in K8S.glob("*.yaml")} - {KUSTOMIZATION.name, STRIMZI_TOPICS.name}
    assert sorted(listed) == sorted(on_disk)
    assert STRIMZI_TOPICS.name not in listed


def test_every_mapservice_variable_is_a_settings_field():
    """Every MAPSERVICE_* name written anywhere in infra/ is a field of Settings."""
    named: dict[str, set[str]] = {}
    for path in INFRA.rglob("*"):
        if path.is_file():
            for var in VAR_NAME.findall(path.read_text()):
                named.setdefault(var, set()).add(str(path.relative_to(ROOT)))
    assert {"MAPSERVICE_MQTT_CLIENT_ID", "MAPSERVICE_ADMIN_TOKEN"} <= named.keys()
    unknown = {var: sorted(files) for var, files in named.items() if var not in SETTINGS_VARS}
    assert not unknown, f"not fields of mapservice.settings.Settings: {unknown}"


def test_compose_components_are_configured_only_through_mapservice_variables():
    """The compose gateway/processors/api get only MAPSERVICE_* variables, no env_file."""
    components = compose_components()
    assert set(components) == COMPONENTS
    for name, svc in components.items():
        assert "env_file" not in svc, name
        keys = set(compose_env(svc))
        assert keys and all(k.startswith("MAPSERVICE_") for k in keys), (name, keys)


def cli_invocations() -> list[tuple[str, list[str]]]:
    found = [
        (f"compose:{name}", [str(a) for a in svc["command"]])
        for name, svc in compose_mapservice().items()
    ]
    found += [(f"k8s:{w['metadata']['name']}", container_argv(c)) for w, c in workloads() + jobs()]
    in_code = False
    for line in INFRA_README.read_text().splitlines():
        if line.lstrip().startswith("```"):
            in_code = not in_code
            continue
        match = re.match(r"^\s*(?:\$\s*)?mapservice\s+(.*)$", line) if in_code else None
        if match:
            found.append(("infra/README.md", shlex.split(match.group(1), comments=True)))
    return found


def test_every_mapservice_subcommand_is_accepted_by_the_cli(monkeypatch):
    """Every `mapservice ...` argv in infra/ parses with the real CLI and reaches its handler."""
    from mapservice import cli
    from mapservice.robot import cli as robot_cli

    invocations = cli_invocations()
    assert {
        argv[0] for where, argv in invocations if where.startswith("compose:")
    } == COMPONENTS | ONE_SHOT
    assert {
        argv[0] for where, argv in invocations if where.startswith("k8s:")
    } == COMPONENTS | ONE_SHOT
    calls: list[tuple[str, dict]] = []
    for module, handler in (
        (cli, "cmd_gateway"),
        (cli, "cmd_serve"),
        (robot_cli, "cmd_sim"),
        (cli, "cmd_up"),
        (cli, "cmd_migrate"),
    ):
        monkeypatch.setattr(
            module, handler, lambda args, _h=handler, **kw: calls.append((_h, {"args": args, **kw}))
        )
    for where, argv in invocations:
        calls.clear()
        try:
            cli.main(argv)
        except SystemExit as exc:
            pytest.fail(f"{where}: `mapservice {' '.join(argv)}` rejected by the CLI ({exc})")
        assert len(calls) == 1, (where, argv)
        args = calls[0][1]["args"]
        if health_port(argv) is not None:
            assert args.health_port == health_port(argv)
    for sub in sorted({argv[0] for _, argv in invocations}):
        done = subprocess.run(
            [sys.executable, "-m", "mapservice.cli", sub, "--help"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 0, f"mapservice {sub} --help: {done.stderr[-500:]}"
    docker = [line for line in DOCKERFILE.read_text().splitlines() if line.startswith("ENTRYPOINT")]
    assert docker == ['ENTRYPOINT ["mapservice"]']


def test_no_secret_value_is_committed():
    """No token or password has a literal value in infra/: compose ${VAR:?...}, k8s secretRef only."""
    # compose: every secret is a required substitution, never a default.
    compose_text = COMPOSE.read_text()
    for name, svc in compose()["services"].items():
        raw = svc.get("environment", {})
        if isinstance(raw, list):
            raw = dict(item.split("=", 1) for item in raw)
        for key, value in raw.items():
            if is_secret_name(key):
                assert SECRET_REF.match(str(value)), f"compose {name}: {key}={value!r}"
    for var, default in re.findall(r"\$\{([A-Za-z0-9_]+)(:?-[^}]*)\}", compose_text):
        assert not is_secret_name(var), f"compose gives {var} a default ({default})"
    # Kubernetes: no Secret, no secret in a ConfigMap or a plain env value.
    for path in K8S.glob("*.yaml"):
        for doc in load_all(path):
            assert doc.get("kind") != "Secret", f"{path.name} commits a Secret"
            if doc.get("kind") == "ConfigMap":
                leaked = [k for k in doc.get("data", {}) if is_secret_name(k)]
                assert not leaked, f"{path.name}: secrets in a ConfigMap: {leaked}"
    for workload, container in workloads():
        for entry in container.get("env", []):
            if is_secret_name(entry["name"]):
                assert "value" not in entry, f"{workload['metadata']['name']}: {entry['name']}"
        refs = [s["secretRef"] for s in container.get("envFrom", []) if "secretRef" in s]
        assert refs == [{"name": "mapservice"}], workload["metadata"]["name"]
    # The MQTT password is per component (each manifest maps its own); EMQX's API secret is
    # the operator's, for `mapservice robot --emqx`, and no pod reads it.
    assert (
        SECRET_VARS - {"MAPSERVICE_MQTT_PASSWORD", "MAPSERVICE_EMQX_API_SECRET"}
        <= secret_keys_from_readme()
    )
    # Dockerfile: no ENV/ARG sets a secret.
    for line in DOCKERFILE.read_text().splitlines():
        if re.match(r"^\s*(ENV|ARG)\b", line):
            assert not any(is_secret_name(v) for v in re.findall(r"[A-Z][A-Z0-9_]+", line)), line
    # Anywhere: `TOKEN=`/`PASSWORD:` is followed by a reference or a placeholder, not a value.
    allowed = ("${", "$(", '"$(', "...", "<", "$")
    for path in [p for p in INFRA.rglob("*") if p.is_file()] + [DOCKERIGNORE]:
        for line in path.read_text().splitlines():
            for key, value in re.findall(
                r"([A-Za-z0-9_]*(?:TOKEN|PASSWORD))[\"']?\s*[:=]\s*[\"']?([^\s\"']*)", line
            ):
                assert value == "" or value.startswith(allowed), (
                    f"{path.relative_to(ROOT)}: {key} has a literal value: {line.strip()}"
                )


def test_compose_file_is_consistent():
    """compose: dependencies, volumes, `$$` escaping, KRaft Kafka on a volume, build of infra/Dockerfile."""
    doc = compose()
    services, volumes = doc["services"], set(doc.get("volumes") or {})
    for name, svc in services.items():
        for dep in svc.get("depends_on", {}):
            assert dep in services, f"{name} depends on unknown {dep}"
            if (
                isinstance(svc["depends_on"], dict)
                and svc["depends_on"][dep].get("condition") != "service_completed_successfully"
            ):
                assert "healthcheck" in services[dep], f"{name} waits for {dep}, which has none"
        for mount in svc.get("volumes", []):
            source = str(mount).split(":")[0]
            if source.startswith("."):
                assert (INFRA / source).exists(), f"{name}: {source} does not exist"
            else:
                assert source in volumes, f"{name}: volume {source} not declared"
    images = {name: str(svc.get("image", "")) for name, svc in services.items()}
    assert images["kafka"].startswith("apache/kafka:")
    assert images["clickhouse"].startswith("clickhouse/clickhouse-server:")
    assert images["mosquitto"].startswith("eclipse-mosquitto:")
    kafka = services["kafka"]["environment"]
    assert set(kafka["KAFKA_PROCESS_ROLES"].split(",")) == {"broker", "controller"}
    assert any(v.endswith(":/var/lib/kafka/data") for v in services["kafka"]["volumes"])
    assert kafka["KAFKA_LOG_DIRS"] == "/var/lib/kafka/data"
    assert SECRET_REF.match(services["clickhouse"]["environment"]["CLICKHOUSE_PASSWORD"])
    # A lone `$` is interpolation to compose: it must be `$$` or `${...}`.
    text = re.sub(r"\$\$|\$\{[^}]*\}", "", COMPOSE.read_text())
    assert "$" not in "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#"))
    build = services["gateway"]["build"]
    assert (INFRA / build["context"] / build["dockerfile"]).resolve() == DOCKERFILE.resolve()


def test_kustomize_renders_the_manifests():
    """`kubectl kustomize infra/k8s` renders every manifest into namespace mapservice (needs kubectl)."""
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        pytest.skip("kubectl is not installed")
    done = subprocess.run(
        [kubectl, "kustomize", str(K8S)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    rendered = [d for d in yaml.safe_load_all(done.stdout) if d]
    assert len(rendered) == len(k8s_docs())
    for doc in rendered:
        if doc["kind"] != "Namespace":
            assert doc["metadata"]["namespace"] == "mapservice", doc["metadata"]["name"]


def test_infra_readme_says_what_was_checked():
    """infra/README.md names this test file and says no Docker engine or cluster was used."""
    text = INFRA_README.read_text()
    assert "tests/infra/test_manifests.py" in text
    assert re.search(r"^docker build -f infra/Dockerfile( -t \S+)? \.$", text, re.M)
    assert "strimzi-topics.yaml" in text
    assert re.search(r"no Docker engine", text, re.I)


def test_dockerfile_installs_the_project_as_a_non_root_mapservice_image():
    """The Dockerfile: the UI built by node, python:3.11-slim, what `pip install .` needs, non-root."""
    lines = [
        ln.strip()
        for ln in DOCKERFILE.read_text().splitlines()
        if ln.strip() and not ln.strip().startswith("#")
    ]
    froms = [ln.split()[1] for ln in lines if ln.startswith("FROM ")]
    assert froms[0].startswith("node:") and "FROM node:20-slim AS ui" in lines, froms
    assert froms[1:] and all(f == "python:3.11-slim" for f in froms[1:]), froms
    assert "RUN npm ci" in lines and "RUN npm run build" in lines
    assert "COPY --from=ui /ui/dist /usr/share/mapservice/ui" in lines
    assert "ENV MAPSERVICE_UI_DIR=/usr/share/mapservice/ui" in lines
    copied = set()
    for ln in lines:
        if ln.startswith("COPY ") and "--from=" not in ln:
            *sources, _dest = ln.split()[1:]
            for src in sources:
                assert (ROOT / src).exists(), f"COPY {src}: not in the build context (repo root)"
                copied.add(src.rstrip("/"))
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    needed = {
        "pyproject.toml",
        pyproject["project"]["readme"],
        *pyproject["tool"]["setuptools"]["package-dir"].values(),
    }
    assert needed <= copied or "." in copied, f"not copied: {needed - copied}"
    assert any(re.search(r"pip install [^\n]*\.$", ln) for ln in lines)
    users = [ln.split()[1] for ln in lines if ln.startswith("USER ")]
    assert users, "the image runs as root"
    uid = users[-1].split(":")[0]
    assert uid.isdigit() and int(uid) != 0, f"USER {users[-1]}: numeric non-root expected"
    assert 'ENTRYPOINT ["mapservice"]' in lines
    ignored = {
        ln.strip().rstrip("/")
        for ln in DOCKERIGNORE.read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    }
    assert {".venv", ".mapservice-data", ".git", "node_modules", "test-artifacts"} <= ignored
    assert not (copied & ignored), f"COPY of ignored paths: {copied & ignored}"
    for workload, _ in workloads():
        pod = workload["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] == int(uid)
