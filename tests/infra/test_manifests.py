"""The deployment files in infra/ agree with the code they deploy.

No Docker engine or Kubernetes cluster is at hand where these tests run, so they check
the files statically against the code itself: the settings object, the CLI's parser,
the real health handlers, the topics the service creates. Two checks use a local tool
when it is installed (mosquitto for the broker config, kubectl for kustomize).
"""

from __future__ import annotations

import re
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import yaml
from pydantic import SecretStr

from mapservice.settings import Settings
from mapservice.adapters.kafka_topics import topic_config, topic_partitions
from tests.fixtures.paths import ROOT

INFRA = ROOT / "infra"
K8S = INFRA / "k8s"
COMPOSE = INFRA / "compose.yaml"
DOCKERFILE = INFRA / "Dockerfile"
MOSQUITTO_CONF = INFRA / "mosquitto" / "mosquitto.conf"
INFRA_README = INFRA / "README.md"
DOCKERIGNORE = ROOT / ".dockerignore"
STRIMZI_TOPICS = K8S / "strimzi-topics.yaml"
KUSTOMIZATION = K8S / "kustomization.yaml"

COMPONENTS = {"gateway", "processors", "api"}
ONE_SHOT = {"migrate"}  # runs to completion once per release
SETTINGS_VARS = {f"MAPSERVICE_{name.upper()}" for name in Settings.model_fields}
# Fields typed SecretStr: admin token and the passwords.
SECRET_VARS = {
    f"MAPSERVICE_{name.upper()}"
    for name, field in Settings.model_fields.items()
    if "SecretStr" in str(field.annotation) or field.annotation is SecretStr
}
# Values used where the real secret is supplied at deploy time.
DUMMY_SECRET = "0123456789abcdef0123456789abcdef"


def dummy_secret(key: str) -> str:
    """The dummy value of a Secret key, in the shape its setting takes."""
    return f"agv-1={DUMMY_SECRET}" if key == "MAPSERVICE_API_ROBOT_TOKENS" else DUMMY_SECRET
SECRET_REF = re.compile(r"^\$\{(?P<var>[A-Za-z_][A-Za-z0-9_]*):\?(?P<msg>[^}]+)\}$")
VAR_NAME = re.compile(r"\bMAPSERVICE_[A-Z0-9_]*[A-Z0-9]\b")


def is_secret_name(name: str) -> bool:
    upper = name.upper()
    return upper in SECRET_VARS or upper.endswith(("_PASSWORD", "_TOKEN", "_SECRET"))


# ---------------------------------------------------------------------------- loading


def yaml_files() -> list[Path]:
    return sorted(p for p in INFRA.rglob("*") if p.suffix in (".yaml", ".yml") and p.is_file())


def load_all(path: Path) -> list:
    return [doc for doc in yaml.safe_load_all(path.read_text()) if doc is not None]


def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def compose_mapservice() -> dict[str, dict]:
    """Compose services that run the mapservice image, by service name."""
    return {name: svc for name, svc in compose()["services"].items()
            if "build" in svc or str(svc.get("image", "")).startswith("mapservice")}


def compose_components() -> dict[str, dict]:
    """The long-running ones (not the one-shot migrate)."""
    return {name: svc for name, svc in compose_mapservice().items() if name not in ONE_SHOT}


def kustomize_resources() -> list[str]:
    return yaml.safe_load(KUSTOMIZATION.read_text())["resources"]


def k8s_docs() -> list[dict]:
    """Every document of the manifests kustomization.yaml deploys."""
    return [doc for name in kustomize_resources() for doc in load_all(K8S / name)]


def jobs() -> list[tuple[dict, dict]]:
    """(job, container) for every container of a Job."""
    return [(doc, c) for doc in k8s_docs() if doc["kind"] == "Job"
            for c in doc["spec"]["template"]["spec"]["containers"]]


def workloads() -> list[tuple[dict, dict]]:
    """(workload, container) for every container of a Deployment or StatefulSet."""
    return [(doc, c) for doc in k8s_docs() if doc["kind"] in ("Deployment", "StatefulSet")
            for c in doc["spec"]["template"]["spec"]["containers"]]


def configmap(name: str) -> dict[str, str]:
    for doc in k8s_docs():
        if doc["kind"] == "ConfigMap" and doc["metadata"]["name"] == name:
            return doc.get("data", {})
    raise AssertionError(f"no ConfigMap {name!r} in {kustomize_resources()}")


def container_argv(container: dict) -> list[str]:
    """The arguments after `mapservice` (the image's entrypoint, or an explicit command)."""
    command = list(container.get("command", []))
    if command:
        assert Path(command[0]).name == "mapservice", f"{container['name']}: command {command}"
        return command[1:] + list(container.get("args", []))
    return list(container.get("args", []))


def health_port(argv: list[str]) -> int | None:
    if "--health-port" in argv:
        return int(argv[argv.index("--health-port") + 1])
    return None


def secret_keys_from_readme() -> set[str]:
    """Keys of the documented `kubectl create secret generic mapservice ...` command."""
    text = INFRA_README.read_text().replace("\\\n", " ")
    commands = [line for line in text.splitlines()
                if "kubectl" in line and "create secret generic mapservice" in line]
    assert commands, "infra/README.md documents no `kubectl create secret generic mapservice`"
    return set(re.findall(r"--from-literal=([A-Z0-9_]+)=", " ".join(commands)))


def k8s_env(workload: dict, container: dict) -> dict[str, str]:
    """What the container's process would see: ConfigMap, Secret (dummy values), env."""
    env: dict[str, str] = {}
    for source in container.get("envFrom", []):
        if "configMapRef" in source:
            env.update(configmap(source["configMapRef"]["name"]))
        if "secretRef" in source:
            env.update({key: dummy_secret(key) for key in secret_keys_from_readme()})
    pod_name = f"{workload['metadata']['name']}-0"
    for entry in container.get("env", []):
        if "value" in entry:
            env[entry["name"]] = str(entry["value"])
        elif entry.get("valueFrom", {}).get("fieldRef", {}).get("fieldPath") == "metadata.name":
            env[entry["name"]] = pod_name
        elif "secretKeyRef" in entry.get("valueFrom", {}):
            env[entry["name"]] = DUMMY_SECRET
    return env


def compose_env(service: dict) -> dict[str, str]:
    """The service's environment with every ${VAR:?...} given a value, as compose would."""
    raw = service.get("environment", {})
    if isinstance(raw, list):
        raw = dict(item.split("=", 1) for item in raw)
    return {key: SECRET_REF.sub(DUMMY_SECRET, str(value)) for key, value in raw.items()}


def settings_from(env: dict[str, str]) -> Settings:
    with pytest.MonkeyPatch.context() as mp:
        for key, value in env.items():
            mp.setenv(key, value)
        return Settings()


# ------------------------------------------------------------- the real health handlers


@pytest.fixture(scope="module")
def served():
    """served(component, path) -> HTTP status from the handler the component really runs."""
    from fastapi.testclient import TestClient

    from mapservice.testing.memory_store import MemoryStore
    from mapservice.api.app import create_app
    from mapservice.runtime.health_server import serve_health

    health = serve_health("127.0.0.1", 0, lambda: {"ok": True})
    port = health.server_address[1]
    api = TestClient(create_app(Settings(), MemoryStore(), {"clickhouse": lambda: True}))

    def status(component: str, path: str) -> int:
        if component == "api":
            return api.get(path).status_code
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as resp:
                return resp.status
        except urllib.error.HTTPError as exc:
            return exc.code

    yield status
    health.shutdown()
    health.server_close()


# -------------------------------------------------------------------------------- tests


def test_every_yaml_file_in_infra_parses():
    """Every YAML file in infra/ parses (all its documents), and the deployment files exist."""
    for path in (COMPOSE, DOCKERFILE, MOSQUITTO_CONF, INFRA_README, KUSTOMIZATION,
                 STRIMZI_TOPICS, DOCKERIGNORE):
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
    found = [(f"compose:{name}", [str(a) for a in svc["command"]])
             for name, svc in compose_mapservice().items()]
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
    assert {argv[0] for where, argv in invocations if where.startswith("compose:")} == COMPONENTS | ONE_SHOT
    assert {argv[0] for where, argv in invocations if where.startswith("k8s:")} == COMPONENTS | ONE_SHOT
    calls: list[tuple[str, dict]] = []
    for module, handler in ((cli, "cmd_gateway"), (cli, "cmd_serve"), (robot_cli, "cmd_sim"),
                            (cli, "cmd_up"), (cli, "cmd_migrate")):
        monkeypatch.setattr(module, handler,
                            lambda args, _h=handler, **kw: calls.append((_h, {"args": args, **kw})))
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
        done = subprocess.run([sys.executable, "-m", "mapservice.cli", sub, "--help"],
                              cwd=ROOT, capture_output=True, text=True, timeout=120)
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
    assert SECRET_VARS - {"MAPSERVICE_MQTT_PASSWORD", "MAPSERVICE_EMQX_API_SECRET"} <= secret_keys_from_readme()
    # Dockerfile: no ENV/ARG sets a secret.
    for line in DOCKERFILE.read_text().splitlines():
        if re.match(r"^\s*(ENV|ARG)\b", line):
            assert not any(is_secret_name(v) for v in re.findall(r"[A-Z][A-Z0-9_]+", line)), line
    # Anywhere: `TOKEN=`/`PASSWORD:` is followed by a reference or a placeholder, not a value.
    allowed = ("${", "$(", '"$(', "...", "<", "$")
    for path in [p for p in INFRA.rglob("*") if p.is_file()] + [DOCKERIGNORE]:
        for line in path.read_text().splitlines():
            for key, value in re.findall(
                    r"([A-Za-z0-9_]*(?:TOKEN|PASSWORD))[\"']?\s*[:=]\s*[\"']?([^\s\"']*)", line):
                assert value == "" or value.startswith(allowed), \
                    f"{path.relative_to(ROOT)}: {key} has a literal value: {line.strip()}"


def test_gateway_statefulset_takes_its_mqtt_client_id_from_the_pod_name():
    """The gateway is a 2-replica StatefulSet sharing `$share/mapservice/`, client id = pod name."""
    gateways = [(w, c) for w, c in workloads() if container_argv(c)[:1] == ["gateway"]]
    assert len(gateways) == 1
    workload, container = gateways[0]
    assert workload["kind"] == "StatefulSet"
    assert workload["spec"]["replicas"] == 2
    env = {e["name"]: e for e in container["env"]}
    assert env["MAPSERVICE_MQTT_CLIENT_ID"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.name"
    assert env["MAPSERVICE_MQTT_SHARE_GROUP"]["value"] == "mapservice"
    settings = settings_from(k8s_env(workload, container))
    assert settings.mqtt_client_id == f"{workload['metadata']['name']}-0"
    assert all(t.startswith("$share/mapservice/") for t in settings.mqtt_subscriptions)
    # compose runs one gateway with a fixed id of its own (not the default).
    gateway = compose_components()["gateway"]
    assert compose_env(gateway)["MAPSERVICE_MQTT_CLIENT_ID"] != Settings().mqtt_client_id
    assert "deploy" not in gateway or gateway["deploy"].get("replicas", 1) == 1


def probes(container: dict) -> dict[str, dict]:
    return {kind: container[kind]["httpGet"]
            for kind in ("startupProbe", "livenessProbe", "readinessProbe") if kind in container}


def resolve_port(container: dict, port) -> int:
    if isinstance(port, int):
        return port
    for p in container.get("ports", []):
        if p.get("name") == port:
            return p["containerPort"]
    raise AssertionError(f"{container['name']}: no container port named {port!r}")


def listen_port(component: str, argv: list[str], env: dict[str, str]) -> int:
    if component == "api":
        return settings_from(env).api_port
    port = health_port(argv)
    assert port is not None, f"{component} runs without --health-port: nothing to probe"
    return port


def test_probes_point_at_paths_and_ports_the_components_serve(served):
    """Probes, scrape annotations and healthchecks hit paths the real handlers answer 200, on the right port."""
    checked = 0
    for workload, container in workloads():
        argv = container_argv(container)
        component = argv[0]
        port = listen_port(component, argv, k8s_env(workload, container))
        found = probes(container)
        assert {"livenessProbe", "readinessProbe"} <= found.keys(), workload["metadata"]["name"]
        for kind, get in found.items():
            assert resolve_port(container, get["port"]) == port, (component, kind)
            assert served(component, get["path"]) == 200, (component, kind, get["path"])
            checked += 1
        assert found["livenessProbe"]["path"] == "/healthz"
        assert found["readinessProbe"]["path"] == "/readyz"
        notes = workload["spec"]["template"]["metadata"]["annotations"]
        assert notes["prometheus.io/scrape"] == "true"
        assert int(notes["prometheus.io/port"]) == port
        assert served(component, notes["prometheus.io/path"]) == 200
        resources = container["resources"]
        assert {"cpu", "memory"} <= resources["requests"].keys() <= resources["limits"].keys()
    for name, svc in compose_components().items():
        argv = [str(a) for a in svc["command"]]
        test = " ".join(str(part) for part in svc["healthcheck"]["test"])
        match = re.search(r"http://(?:127\.0\.0\.1|localhost):(\d+)(/[A-Za-z0-9_/-]*)", test)
        assert match, f"compose {name}: healthcheck is not an HTTP check: {test}"
        assert int(match.group(1)) == listen_port(argv[0], argv, compose_env(svc)), name
        assert match.group(2) == "/readyz", name
        assert served(argv[0], match.group(2)) == 200
        checked += 1
    assert checked >= 3 * 3 + 3
    # The handlers really distinguish: a path they do not serve is not 200.
    assert served("gateway", "/livez") != 200
    assert served("api", "/no-such-path") != 200


def test_the_api_as_deployed_guards_metrics_and_docs_but_not_probes():
    """With the k8s ConfigMap and Secret, the API's probes answer without a token, /metrics and
    /openapi.json only with one, and the PodMonitor scrapes with the Secret's metrics token."""
    from fastapi.testclient import TestClient

    from mapservice.testing.memory_store import MemoryStore
    from mapservice.api.app import create_app

    [(workload, container)] = [(w, c) for w, c in workloads() if container_argv(c)[:1] == ["api"]]
    settings = settings_from(k8s_env(workload, container))
    assert (settings.metrics_access, settings.docs_access, settings.api_read_access) == (
        "token", "token", "open")
    api = TestClient(create_app(settings, MemoryStore(), {"clickhouse": lambda: True}))
    for kind, get in probes(container).items():
        assert api.get(get["path"]).status_code == 200, kind
    token = {"Authorization": f"Bearer {DUMMY_SECRET}"}  # every Secret key holds it here
    for path in ("/metrics", "/openapi.json"):
        assert api.get(path).status_code == 401, path
        assert api.get(path, headers=token).status_code == 200, path
    [monitor] = load_all(K8S / "monitoring" / "podmonitor.yaml")
    [http] = [e for e in monitor["spec"]["podMetricsEndpoints"] if e["port"] == "http"]
    assert http["authorization"] == {"type": "Bearer", "credentials": {
        "name": "mapservice", "key": "MAPSERVICE_API_METRICS_TOKEN"}}
    assert "MAPSERVICE_API_METRICS_TOKEN" in secret_keys_from_readme()


def test_probed_components_listen_on_all_interfaces():
    """Everything probed binds 0.0.0.0 (MAPSERVICE_API_HOST also binds the health servers)."""
    for workload, container in workloads():
        settings = settings_from(k8s_env(workload, container))
        assert settings.api_host == "0.0.0.0", workload["metadata"]["name"]
    for name, svc in compose_components().items():
        assert settings_from(compose_env(svc)).api_host == "0.0.0.0", name


def test_each_component_environment_gives_valid_production_settings():
    """Each component's env loads as production Settings (server DSN, rebalance >= 10 s), not without its token."""
    envs = [(f"compose:{n}", compose_env(s)) for n, s in compose_components().items()]
    envs += [(f"k8s:{w['metadata']['name']}", k8s_env(w, c)) for w, c in workloads()]
    assert len(envs) == 6
    for where, env in envs:
        settings = settings_from(env)
        assert settings.mode == "production", where
        assert settings.resolved_clickhouse_dsn.startswith(("http://", "https://")), where
        assert settings.kafka_rebalance_timeout_s >= 10, where
        assert settings.admin_token.get_secret_value() == DUMMY_SECRET, where
        assert settings.clickhouse_password.get_secret_value() == DUMMY_SECRET, where
        without_token = {k: v for k, v in env.items() if k != "MAPSERVICE_ADMIN_TOKEN"}
        with pytest.raises(ValueError, match="ADMIN_TOKEN"):
            settings_from(without_token)
    assert compose_env(compose()["services"]["gateway"])["MAPSERVICE_CLICKHOUSE_DSN"] \
        == "http://clickhouse:8123"


def test_strimzi_topics_match_the_settings():
    """strimzi-topics.yaml has the five Settings topics, ConfigMap partitions/replicas, and
    exactly the configs the service creates topics with (mapservice.adapters.kafka_topics.topic_config):
    retention as the history's, meta compacted x1, live x1 with the live retention."""
    settings = settings_from({**configmap("mapservice"), "MAPSERVICE_ADMIN_TOKEN": DUMMY_SECRET,
                              "MAPSERVICE_CLICKHOUSE_PASSWORD": DUMMY_SECRET})
    docs = load_all(STRIMZI_TOPICS)
    assert all(d["kind"] == "KafkaTopic" and d["apiVersion"].startswith("kafka.strimzi.io/")
               for d in docs)
    topics = {d["spec"].get("topicName", d["metadata"]["name"]): d for d in docs}
    assert sorted(topics) == sorted(settings.kafka_topics)
    for name, doc in topics.items():
        spec = doc["spec"]
        meta = name in (settings.topic_meta_events, settings.topic_annotation_events)
        assert spec["partitions"] == topic_partitions(settings, name), name
        if name == settings.topic_live:
            assert spec["config"]["retention.ms"] == settings.live_retention_s * 1000
        assert spec["replicas"] == settings.kafka_replication, name
        assert spec.get("config", {}).get("cleanup.policy", "delete") == (
            "compact" if meta else "delete"), name
        assert {k: str(v) for k, v in spec.get("config", {}).items()} == topic_config(settings, name), name
        cluster = doc["metadata"]["labels"]["strimzi.io/cluster"]
        assert settings.kafka_bootstrap.startswith(f"{cluster}-kafka-bootstrap."), name


def test_dockerfile_installs_the_project_as_a_non_root_mapservice_image():
    """The Dockerfile: the UI built by node, python:3.11-slim, what `pip install .` needs, non-root."""
    lines = [ln.strip() for ln in DOCKERFILE.read_text().splitlines()
             if ln.strip() and not ln.strip().startswith("#")]
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
    needed = {"pyproject.toml", pyproject["project"]["readme"],
              *pyproject["tool"]["setuptools"]["package-dir"].values()}
    assert needed <= copied or "." in copied, f"not copied: {needed - copied}"
    assert any(re.search(r"pip install [^\n]*\.$", ln) for ln in lines)
    users = [ln.split()[1] for ln in lines if ln.startswith("USER ")]
    assert users, "the image runs as root"
    uid = users[-1].split(":")[0]
    assert uid.isdigit() and int(uid) != 0, f"USER {users[-1]}: numeric non-root expected"
    assert 'ENTRYPOINT ["mapservice"]' in lines
    ignored = {ln.strip().rstrip("/") for ln in DOCKERIGNORE.read_text().splitlines()
               if ln.strip() and not ln.startswith("#")}
    assert {".venv", ".mapservice-data", ".git", "node_modules", "test-artifacts"} <= ignored
    assert not (copied & ignored), f"COPY of ignored paths: {copied & ignored}"
    for workload, _ in workloads():
        pod = workload["spec"]["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] == int(uid)


def test_mosquitto_conf_has_the_tuning_the_gateway_relies_on():
    """mosquitto.conf sets nodelay, 1000 in flight, a large queue, persistence and a
    WebSocket listener for browsers; compose mounts it and tells the API where it is."""
    options: dict[str, str] = {}
    listeners: list[str] = []
    for line in MOSQUITTO_CONF.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, value = line.strip().partition(" ")
            options[key] = value.strip()
            if key == "listener":
                listeners.append(value.strip())
            elif key == "protocol":
                listeners[-1] += f" {value.strip()}"
    assert listeners == ["1883", "9001 websockets"]
    assert options["set_tcp_nodelay"] == "true"
    assert int(options["max_inflight_messages"]) == 1000
    assert int(options["max_queued_messages"]) >= 100_000
    assert options["persistence"] == "true"
    services = compose()["services"]
    assert "/mosquitto/data" in " ".join(services["mosquitto"]["volumes"])
    assert "./mosquitto/mosquitto.conf:/mosquitto/config/mosquitto.conf:ro" in \
        services["mosquitto"]["volumes"]
    # The /controller page reaches the WebSocket listener through the published port.
    assert "9001:9001" in services["mosquitto"]["ports"]
    assert services["api"]["environment"]["MAPSERVICE_MQTT_WS_URL"] == "ws://localhost:9001"
    assert compose_env(services["gateway"])["MAPSERVICE_MQTT_URL"] == "mqtt://mosquitto:1883"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_shipped_mosquitto_saves_its_store_as_often_as_the_embedded_one():
    """infra's Mosquitto persists sessions and queued messages and saves them every second, as the fault-tested embedded broker does."""
    from mapservice.local.embedded import MOSQUITTO_STORE

    lines = MOSQUITTO_CONF.read_text().splitlines()
    assert "persistence true" in lines
    (shipped,) = [line for line in lines if line.startswith("autosave_interval")]
    assert shipped in MOSQUITTO_STORE.splitlines() and shipped == "autosave_interval 1"


def test_mosquitto_starts_with_the_config():
    """The local mosquitto starts with infra/mosquitto/mosquitto.conf (port and data path changed only)."""
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not Path(binary).exists():
        pytest.skip("mosquitto is not installed (make test installs it)")
    with tempfile.TemporaryDirectory(prefix="mapservice-mosquitto-") as tmp:
        # As root, mosquitto drops to its own user: let it write its data here.
        Path(tmp).chmod(0o777)
        run_mosquitto(binary, Path(tmp))


def run_mosquitto(binary: str, tmp_path: Path) -> None:
    port = free_port()
    text, n_listener = re.subn(r"(?m)^listener 1883$", f"listener {port} 127.0.0.1",
                               MOSQUITTO_CONF.read_text())
    ws_port = free_port()
    text = re.sub(r"(?m)^listener 9001$", f"listener {ws_port} 127.0.0.1", text)
    text, n_data = re.subn(r"(?m)^persistence_location .*$", f"persistence_location {tmp_path}/",
                           text)
    assert n_listener == 1 and n_data == 1
    conf = tmp_path / "mosquitto.conf"
    conf.write_text(text)
    proc = subprocess.Popen([binary, "-c", str(conf)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                pytest.fail(f"mosquitto refused the config: {proc.stdout.read()}")
            try:
                for p in (port, ws_port):
                    socket.create_connection(("127.0.0.1", p), timeout=0.5).close()
                break
            except OSError:
                time.sleep(0.1)
        else:
            pytest.fail("mosquitto did not listen within 10 s")
    finally:
        proc.terminate()
        proc.wait(10)


def test_compose_file_is_consistent():
    """compose: dependencies, volumes, `$$` escaping, KRaft Kafka on a volume, build of infra/Dockerfile."""
    doc = compose()
    services, volumes = doc["services"], set(doc.get("volumes") or {})
    for name, svc in services.items():
        for dep in svc.get("depends_on", {}):
            assert dep in services, f"{name} depends on unknown {dep}"
            if isinstance(svc["depends_on"], dict) and \
                    svc["depends_on"][dep].get("condition") != "service_completed_successfully":
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
    done = subprocess.run([kubectl, "kustomize", str(K8S)], capture_output=True, text=True,
                          timeout=120)
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


def test_migrations_run_once_per_release_before_the_components():
    """A k8s Job named after the schema version and a compose one-shot run `mapservice migrate`
    in production mode; compose's processors and API start only after it succeeded."""
    from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION

    ((job, container),) = jobs()
    assert job["metadata"]["name"] == f"mapservice-migrate-v{SCHEMA_VERSION}"
    assert container_argv(container) == ["migrate"]
    assert job["spec"]["template"]["spec"]["restartPolicy"] in ("OnFailure", "Never")
    compose_migrate = compose()["services"]["migrate"]
    assert compose_migrate["command"] == ["migrate"] and compose_migrate["restart"] == "no"
    for where, env in (("k8s", k8s_env(job, container)), ("compose", compose_env(compose_migrate))):
        settings = settings_from(env)
        assert settings.mode == "production" and not settings.migrates_on_start, where
    for name in ("processors", "api"):
        assert compose()["services"][name]["depends_on"]["migrate"] == {
            "condition": "service_completed_successfully"}, name
    for workload, container in workloads():  # nobody else migrates in production mode
        assert not settings_from(k8s_env(workload, container)).migrates_on_start


def test_the_schema_cluster_is_the_installations_replicated_cluster():
    """MAPSERVICE_CLICKHOUSE_CLUSTER names a cluster of the ClickHouseInstallation that has
    two or more replicas and a Keeper (what Replicated tables ON CLUSTER need)."""
    (chi,) = [d for d in load_all(K8S / "platform" / "clickhouse.yaml")
              if d["kind"] == "ClickHouseInstallation"]
    clusters = {c["name"]: c["layout"] for c in chi["spec"]["configuration"]["clusters"]}
    name = configmap("mapservice")["MAPSERVICE_CLICKHOUSE_CLUSTER"]
    assert name in clusters and clusters[name]["replicasCount"] >= 2
    assert chi["spec"]["configuration"]["zookeeper"]["nodes"]
    host = settings_from({**configmap("mapservice"), "MAPSERVICE_ADMIN_TOKEN": DUMMY_SECRET,
                          "MAPSERVICE_CLICKHOUSE_PASSWORD": DUMMY_SECRET}).resolved_clickhouse_dsn
    assert f"clickhouse-{chi['metadata']['name']}." in host  # the operator's Service for the CHI
