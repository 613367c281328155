"""Analysts against the running embedded service (`mapservice serve` owning chDB, with a few
hours of simulated history): the guide's examples, clickhouse-connect read-only at the
API's /clickhouse, the guide's own snippets, `mapservice sql` and `mapservice export`.

Bounded: writing the history takes ~10 s, the stack ~30 s, each query well under a second."""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import clickhouse_connect
import httpx
import pytest
from mcap.reader import make_reader

from mapservice.core.wire2019 import encode_coordinates, format_timestamp
from mapservice.local.stack import Stack
from mapservice.runtime.secrets import OPERATOR_TOKEN_FILE, stored_secret
from mapservice.sql.credentials import analyst_password_file
from tests.fixtures import vda5050 as vda
from tests.fixtures.paths import ROOT
from tests.mapservice.sql.attacks import ATTACKS

from .test_pipeline import publish_all

GUIDE = ROOT / "docs" / "analysts.md"


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """Six hours of three simulated robots, then brokers, `serve` and the gateway; one
    message the gateway refuses (so the dead-letter example has a row), a pose inside a
    keep-out zone drawn through the API (so the keep-out example has one), and a VDA 5050
    vehicle that comes online, sends its factsheet, reports an error and loses its
    connection (the vehicle examples)."""
    data_dir = tmp_path_factory.mktemp("analysts") / ".mapservice-data"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "demo-history",
            "--data-dir",
            str(data_dir),
            "--days",
            "0.25",
            "--robots",
            "3",
        ],
        check=True,
        timeout=300,
        capture_output=True,
    )
    stack = Stack(data_dir, mqtt="mosquitto")
    with stack.running():
        publish_all(stack, [("iot/coordinates/sim-000", b"{not json")] + vda_vehicle_messages())
        stand_in_a_keep_out_zone(stack)
        yield stack


def stand_in_a_keep_out_zone(stack) -> None:
    """A keep-out zone drawn with the operator's token; once the store holds it, a pose
    inside it (the processors check poses against the zones they have stored)."""
    token = stored_secret(stack.data_dir, OPERATOR_TOKEN_FILE)
    square = [[0.5, 0.5], [2.5, 0.5], [2.5, 2.5], [0.5, 2.5]]
    r = httpx.post(
        f"{stack.api_url}/api/v1/annotations",
        timeout=30,
        headers={"Authorization": f"Bearer {token}"},
        json={"shape": "zone", "name": "spill", "kind": "keep_out", "polygon": square},
    )
    assert r.status_code == 201, r.text
    created = r.json()["created_ms"]
    deadline = time.monotonic() + 60
    while not httpx.get(
        f"{stack.api_url}/api/v1/annotations/edits",
        timeout=30,
        params={"from": created, "to": created + 1},
    ).json()["edits"]:
        assert time.monotonic() < deadline, "the zone was not stored within 60 s"
        time.sleep(0.5)
    stamp = format_timestamp(max(created + 1000, int(time.time() * 1000)))
    publish_all(
        stack,
        [
            (
                "iot/coordinates/sim-001",
                encode_coordinates("sim-001", stamp, 1.5, 1.5, (0.0, 0.0, 0.0, 1.0)),
            )
        ],
    )


def vda_vehicle_messages() -> list[tuple[str, bytes]]:
    now = int(time.time() * 1000)
    v, m, s = "2.1.0", "Acme", "an-1"
    sheet = vda.factsheet(v, m, s, now - 60_000)
    sheet["typeSpecification"]["seriesName"] = "Tugger 3"
    return [
        (f"uagv/v2/{m}/{s}/{sub}", vda.encode(msg))
        for sub, msg in (
            ("connection", vda.connection(v, m, s, now - 60_000, "ONLINE")),
            ("factsheet", sheet),
            (
                "state",
                vda.state(v, m, s, now - 50_000, errors=(("WARNING", "lowBattery", "charge me"),)),
            ),
            (
                "state",
                vda.state(v, m, s, now - 49_000, errors=(("WARNING", "lowBattery", "charge me"),)),
            ),
            ("connection", vda.connection(v, m, s, now - 45_000, "OFFLINE")),
        )
    ]


@pytest.fixture(scope="module")
def password(stack) -> str:
    return analyst_password_file(stack.data_dir).read_text().strip()


def analyst(stack, password: str, **kw):
    port = int(stack.api_url.rsplit(":", 1)[1])
    return clickhouse_connect.get_client(
        host="127.0.0.1",
        port=port,
        username="analyst",
        password=password,
        proxy_path="/clickhouse",
        **kw,
    )


def guide_examples() -> list[tuple[str, str, list[str]]]:
    """(title, sql, columns the guide says it returns) of each 'Common questions' example."""
    text = GUIDE.read_text().split("## Common questions", 1)[1].split("## Reference", 1)[0]
    examples = []
    for section in text.split("\n### ")[1:]:
        title = section.splitlines()[0]
        sql = section.split("```sql\n", 1)[1].split("```", 1)[0]
        returns = section.split("Returns ", 1)[1].split(":", 1)[0]
        examples.append((title, sql, re.findall(r"`([a-z0-9_]+)`", returns)))
    return examples


def test_the_guide_has_an_example_per_common_question() -> None:
    """Eight questions the issue names, the robots inside keep-out zones, two of VDA 5050
    vehicles and the heatmaps, each with its query and its columns."""
    titles = [t for t, _, _ in guide_examples()]
    assert len(titles) == 12 and all(columns for _, _, columns in guide_examples()), titles


@pytest.mark.parametrize("title,sql,columns", guide_examples(), ids=lambda v: str(v)[:40])
def test_every_guide_example_returns_what_the_guide_says(
    stack, password, title, sql, columns
) -> None:
    """Each example runs read-only on the live service and returns rows with the named columns."""
    deadline = time.monotonic() + 60  # the refused message reaches dead_letters within seconds
    while True:
        result = analyst(stack, password).query(sql)
        if result.result_rows or time.monotonic() > deadline:
            break
        time.sleep(1)
    assert list(result.column_names) == columns, title
    assert result.result_rows, f"{title}: no rows"


def test_the_vehicle_examples_hold_the_vehicles_facts(stack, password) -> None:
    """The VDA 5050 examples: the vehicle's warning (two states), its one offline span with
    its factsheet's series, counted from its OFFLINE message's instant."""
    examples = {title: sql for title, sql, _ in guide_examples()}
    client = analyst(stack, password)
    deadline = time.monotonic() + 60
    while not (
        errors := client.query(examples["Errors and warnings of VDA 5050 vehicles"]).result_rows
    ):
        assert time.monotonic() < deadline, "the vehicle's errors were never stored"
        time.sleep(1)
    assert [r[:4] + r[6:] for r in errors] == [
        ("Acme:an-1", "WARNING", "lowBattery", "charge me", 2)
    ]
    assert (errors[0][5] - errors[0][4]).total_seconds() == 1.0
    offline = client.query(examples["Time VDA 5050 vehicles were offline"]).result_rows
    assert [r[:3] for r in offline] == [("Acme:an-1", "Tugger 3", 1)]
    since = client.query(
        "SELECT dateDiff('millisecond', at, now64(3)) / 1000 FROM "
        "mapservice.vehicle_connections WHERE state = 'OFFLINE'"
    ).result_rows[0][0]
    assert 45 <= since and abs(offline[0][3] - since) < 5


def test_clickhouse_connect_reads_but_cannot_write(stack, password) -> None:
    """The analyst reads through clickhouse-connect; inserts, DDL and settings changes are refused."""
    client = analyst(stack, password)
    assert client.query("SELECT count() FROM mapservice.robot_poses").result_rows[0][0] > 10_000
    with pytest.raises(Exception, match="164"):
        client.insert("mapservice.dead_letters", [["x"]], column_names=["reason"])
    with pytest.raises(Exception, match="164"):
        client.command("DROP TABLE mapservice.poses")
    with pytest.raises(Exception, match="164"):
        client.query("SELECT 1 SETTINGS max_execution_time = 100000")
    assert client.query("SELECT count() FROM mapservice.poses").result_rows[0][0] > 10_000


def test_without_the_credential_nothing_runs(stack, password) -> None:
    """No password, a wrong one, or the service's own user: refused with 516."""
    url = f"{stack.api_url}/clickhouse/"
    assert httpx.post(url, content=b"SELECT 1").status_code == 403
    assert httpx.post(url, content=b"SELECT 1", auth=("analyst", password + "x")).status_code == 403
    assert httpx.post(url, content=b"SELECT 1", auth=("default", "")).status_code == 403
    with pytest.raises(Exception, match="516"):
        analyst(stack, "wrong")


def guide_block(language: str, index: int) -> str:
    return GUIDE.read_text().split(f"```{language}\n")[index + 1].split("```", 1)[0]


def test_the_guides_python_and_curl_snippets_run(stack) -> None:
    """The guide's Python and curl blocks, pointed at this stack's port, print results."""
    port = stack.api_url.rsplit(":", 1)[1]
    python = guide_block("python", 0).replace("port=8080", f"port={port}")
    done = subprocess.run(
        [sys.executable, "-c", python],
        cwd=stack.data_dir.parent,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert "sim-000" in done.stdout
    curl = guide_block("bash", 1).replace("127.0.0.1:8080", f"127.0.0.1:{port}")
    done = subprocess.run(
        ["bash", "-c", curl], cwd=stack.data_dir.parent, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0 and int(done.stdout) > 10_000, done.stderr


def test_mapservice_sql_prints_the_result(stack) -> None:
    """`mapservice sql` finds the generated password in the data dir and prints the rows."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "sql",
            "--url",
            f"{stack.api_url}/clickhouse",
            "--data-dir",
            str(stack.data_dir),
            "--format",
            "JSONEachRow",
            "SELECT robot_id, count() AS n FROM mapservice.robot_poses GROUP BY robot_id ORDER BY robot_id",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    rows = [json.loads(line) for line in done.stdout.splitlines()]
    # The three simulated robots and the fixture's VDA 5050 vehicle (its states carry a pose).
    assert [r["robot_id"] for r in rows] == ["Acme:an-1", "sim-000", "sim-001", "sim-002"]
    refused = subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "sql",
            "--url",
            f"{stack.api_url}/clickhouse",
            "--data-dir",
            str(stack.data_dir),
            "TRUNCATE TABLE mapservice.poses",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert refused.returncode != 0 and "Code: 164" in refused.stderr and "reads" in refused.stderr


def test_mapservice_export_writes_mcap_and_parquet(stack, tmp_path) -> None:
    """`mapservice export`: an hour as MCAP (map and three robots) and as Parquet."""
    now = int(time.time() * 1000)
    window = [
        "--from",
        str(now - 2 * 3_600_000),
        "--to",
        str(now - 3_600_000),
        "--api",
        stack.api_url,
    ]
    out = tmp_path / "hour.mcap"
    subprocess.run(
        [sys.executable, "-m", "mapservice.cli", "export", "replay", *window, "--out", str(out)],
        check=True,
        timeout=120,
        capture_output=True,
    )
    summary = make_reader(io.BytesIO(out.read_bytes())).get_summary()
    topics = {
        summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()
    }
    assert topics["/map"] >= 1
    assert {t for t in topics if t.endswith("/pose")} == {
        f"/robots/sim-00{i}/pose" for i in range(3)
    }
    assert {t for t in topics if t.endswith("/state")} == {
        f"/robots/sim-00{i}/state" for i in range(3)
    }
    assert all(
        n >= 1000 for t, n in topics.items() if t.endswith(("/pose", "/state"))
    )  # a report every 3 s
    parquet = tmp_path / "poses.parquet"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "mapservice.cli",
            "export",
            "robot-poses",
            *window,
            "--format",
            "parquet",
            "--robot",
            "sim-001",
            "--out",
            str(parquet),
        ],
        check=True,
        timeout=120,
        capture_output=True,
    )
    assert parquet.read_bytes()[:4] == b"PAR1" and parquet.stat().st_size > 10_000


@pytest.mark.parametrize("name,template", ATTACKS, ids=[a[0] for a in ATTACKS])
def test_no_attack_reads_a_secret_of_the_running_service(stack, password, name, template) -> None:
    """The attack suite against `serve`'s /clickhouse with the data dir's real secrets (the
    generated admin token among them): each refused with 497 naming what, none leaks."""
    secret = stack.data_dir / "secrets" / "admin-token"
    token = secret.read_text().strip()
    sql = template.format(data=stack.data_dir, secret=secret)
    reply = httpx.post(
        f"{stack.api_url}/clickhouse/", content=sql.encode(), auth=("analyst", password), timeout=30
    )
    assert reply.status_code == 403 and reply.headers["X-ClickHouse-Exception-Code"] == "497", (
        reply.text
    )
    assert re.search(r"is not (allowed|readable)|has a line break", reply.text), reply.text
    assert token not in reply.text and password not in reply.text


@pytest.mark.alone  # times a route while 30 statements sleep
def test_sleeping_analysts_get_too_many_queries_and_the_api_does_not_wait(stack, password) -> None:
    """30 concurrent `SELECT sleep(3)` (the issue: 60 stalled every sync route for a minute):
    at most the pool and its queue (2 + 8) are taken in, the others get 503 with
    Retry-After at once, and the API's own routes answer meanwhile (generous bound: 2 s)."""
    url = f"{stack.api_url}/clickhouse/"

    def sleep_query(_):
        return httpx.post(url, content=b"SELECT sleep(3)", auth=("analyst", password), timeout=60)

    with ThreadPoolExecutor(30) as pool:
        sleeping = [pool.submit(sleep_query, i) for i in range(30)]
        time.sleep(0.5)
        started = time.monotonic()
        robots = httpx.get(f"{stack.api_url}/api/v1/robots", timeout=30)
        robots_s = time.monotonic() - started
        replies = [f.result() for f in sleeping]
    assert robots.status_code == 200 and robots_s < 2.0, robots_s
    busy = [r for r in replies if r.status_code == 503]
    assert len(busy) >= 30 - 10 and all(r.status_code in (200, 503) for r in replies)
    assert all("Too many queries" in r.text and r.headers.get("Retry-After") for r in busy)
