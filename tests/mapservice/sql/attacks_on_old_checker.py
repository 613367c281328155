"""Runs the attack suite's statements through the analysts' checker of another revision
(default: main) over chDB, with a data dir holding a secret, and prints for each whether
the secret came back or what refused it. Evidence that the attacks worked before the
allow-list, and do not after:

    .venv/bin/python -m tests.mapservice.sql.attacks_on_old_checker 33efe9d  # 13 of 47 leak, 15 more run
    .venv/bin/python -m tests.mapservice.sql.attacks_on_old_checker HEAD     # 0 of 47, each 497
"""

from __future__ import annotations

import importlib.util
import inspect
import subprocess
import sys
import tempfile
from pathlib import Path

from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlError, SqlRequest
from mapservice.sql.read_only import ReadOnlyLimits
from tests.mapservice.sql.attacks import ATTACKS

MARKER = "admin-token-that-must-not-leak"


def old_checker(revision: str):
    source = subprocess.run(
        ["git", "show", f"{revision}:mapservice/sql/read_only.py"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = Path(tempfile.mkdtemp()) / "read_only_old.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("read_only_old", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["read_only_old"] = module
    spec.loader.exec_module(module)
    return module.check_read_only


def main(revision: str) -> int:
    check = old_checker(revision)
    data = Path(tempfile.mkdtemp()) / ".mapservice-data"
    (data / "secrets").mkdir(parents=True)
    (data / "secrets" / "admin-token").write_text(MARKER + "\n")
    (data / "secrets" / "robots.json").write_text('{"r1": "' + MARKER + '"}')
    engine = ChdbEngine(data / "clickhouse", read_only_settings=ReadOnlyLimits().settings())
    engine.execute(SqlRequest("CREATE DATABASE IF NOT EXISTS mapservice"))
    leaked = 0
    for name, template in ATTACKS:
        sql = template.format(data=data, secret=data / "secrets" / "admin-token")
        try:
            if len(inspect.signature(check).parameters) == 3:  # the allow-list's checker
                request = SqlRequest(sql, database="mapservice", read_only=True)
                checked = check(engine, request, "mapservice")
            else:
                request = SqlRequest(sql, read_only=True)
                checked = check(engine, request)
            body = engine.execute(
                SqlRequest(checked, database=request.database, read_only=True)
            ).body.decode("utf-8", "replace")
            outcome = "LEAKED the secret" if MARKER in body else f"ran: {body[:60]!r}"
            leaked += MARKER in body
        except SqlError as exc:
            outcome = f"error {exc.code}: {str(exc)[:90]}"
        print(f"{name:45} {outcome}")
    engine.close()
    print(f"{leaked} of {len(ATTACKS)} statements returned the secret at {revision}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "main"))
