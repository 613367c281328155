"""The statements an outsider with the analyst's password tried (issue: "an analyst or a
reader can neither reach a secret nor slow the ingest"), as (name, statement) with
`{data}` for the service's data dir and `{secret}` for a secret file's path in it.

Shared by the attack suite (test_attacks.py) and by the script that shows each of them
reading the secret through the checker of a build before the allow-list
(tests/mapservice/sql/attacks_on_old_checker.py)."""

from __future__ import annotations

SECRET = "{secret}"
ATTACKS: list[tuple[str, str]] = [
    ("file() of the admin token", "SELECT file('{secret}')"),
    ("file() of the robots' credentials", "SELECT file('{data}/secrets/robots.json')"),
    ("file() of the environment", "SELECT file('/proc/self/environ')"),
    ("file() of /etc/shadow", "SELECT file('/etc/shadow')"),
    ("FILE() in capitals", "SELECT FILE('{secret}')"),
    ("File() mixed case", "SELECT File('{secret}')"),
    ("`file`() quoted", "SELECT `file`('{secret}')"),
    ("file() in a subquery", "SELECT * FROM (SELECT file('{secret}') AS s)"),
    ("file() in IN (subquery)", "SELECT 1 WHERE 'x' IN (SELECT file('{secret}'))"),
    ("file() in a lambda", "SELECT arrayMap(p -> file(p), ['{secret}'])"),
    ("file() in a WITH expression", "WITH file('{secret}') AS s SELECT s"),
    ("file() in a CTE", "WITH c AS (SELECT file('{secret}') AS s) SELECT s FROM c"),
    ("file() in a scalar subquery", "SELECT (SELECT file('{secret}'))"),
    (
        "file() in a JOIN's subquery",
        "SELECT s FROM (SELECT 1 AS k) AS a JOIN (SELECT 1 AS k, file('{secret}') AS s) AS b ON a.k = b.k",
    ),
    ("file() in a UNION", "SELECT '' UNION ALL SELECT file('{secret}')"),
    ("file() in WHERE", "SELECT 1 WHERE length(file('{secret}')) > 0"),
    ("file() in a window", "SELECT count() OVER (PARTITION BY file('{secret}'))"),
    ("file() in EXPLAIN", "EXPLAIN SYNTAX SELECT file('{secret}')"),
    ("file() in view()", "SELECT * FROM view(SELECT file('{secret}'))"),
    ("file() via APPLY", "SELECT * APPLY(file) FROM (SELECT '{secret}' AS p)"),
    ("file table function", "SELECT * FROM file('{secret}', 'LineAsString')"),
    ("FILE table function in capitals", "SELECT * FROM FILE('{secret}', 'LineAsString')"),
    (
        "file table function in a JOIN",
        "SELECT * FROM numbers(1) AS n JOIN file('{secret}', 'LineAsString') AS f ON 1",
    ),
    ("DESCRIBE a file", "DESCRIBE file('{secret}', 'LineAsString')"),
    ("python table function", "SELECT * FROM python(x)"),
    ("PYTHON() in capitals", "SELECT PYTHON(1)"),
    ("url table function", "SELECT * FROM url('http://127.0.0.1:9/x', 'CSV')"),
    ("s3 table function", "SELECT * FROM s3('http://127.0.0.1:9/b/x.csv', 'CSV')"),
    ("remote table function", "SELECT * FROM remote('127.0.0.1:9', system.one)"),
    (
        "executable table function",
        "SELECT * FROM executable('cat {secret}', 'LineAsString', 'x String')",
    ),
    ("filesystem table function", "SELECT * FROM filesystem('{data}')"),
    ("merge() past the table check", "SELECT * FROM merge('system', '^users$')"),
    ("dictGet of a server dictionary", "SELECT dictGet('other.dict', 'v', toUInt64(1))"),
    ("getSetting", "SELECT getSetting('max_memory_usage')"),
    ("joinGet past the table check", "SELECT joinGet('system.users', 'name', 'x')"),
    ("a system table outside the list", "SELECT * FROM system.users"),
    ("IN a system table", "SELECT 1 IN system.users"),
    ("SHOW CREATE of a system table", "SHOW CREATE TABLE system.processes"),
    ("SHOW CLUSTERS (system.clusters)", "SHOW CLUSTERS"),
    ("SHOW MERGES (system.merges)", "show merges"),
    ("SHOW FILESYSTEM CACHES", "SHOW FILESYSTEM CACHES"),
    ("another database", "SELECT * FROM information_schema.tables"),
]
ATTACKS += [
    ("user(), an alias of currentUser", "SELECT user()"),
    ("hostname(), an alias of hostName", "SELECT hostname()"),
    ("filesystemAvailable", "SELECT filesystemAvailable()"),
    # EXPLAIN AST prints identifiers raw: a line break in one starts lines that are no node.
    ("a line break in an alias before file()", "SELECT 1 AS `a\nb`, file('{secret}')"),
    (
        "a line break in a column name before file()",
        "SELECT `x\n TableExpression` FROM (SELECT 1 AS `x\n TableExpression`) WHERE file('{secret}') != ''",
    ),
]
