"""What analysts see in the schema: table and column comments (table_comments.py), and
views with clean types and units (analyst_views.py), rendered here as the statements of the
migrations that apply them and as docs/analysts.md's reference.

Migration 7 applies the first ones (mapservice/adapters/clickhouse/schema.py); docs/analysts.md
documents every table, view and column named there, and a test holds the two together."""

from __future__ import annotations

from mapservice.adapters.clickhouse.analyst_views import LATER_VIEWS, VIEWS
from mapservice.adapters.clickhouse.table_comments import LATER_TABLE_COMMENTS, TABLE_COMMENTS


def comments_of(*tables: str) -> dict[str, tuple[str, dict[str, str]]]:
    """The comments of some later tables (each migration applies those of its own)."""
    return {t: LATER_TABLE_COMMENTS[t] for t in tables}


def later_view_statements(db: str, *views: str) -> list[str]:
    return [
        f"CREATE OR REPLACE VIEW {db}.{view} AS {LATER_VIEWS[view][1].format(db=db)} "
        f"COMMENT {_quote(LATER_VIEWS[view][0])}"
        for view in views
    ]


def _quote(text: str) -> str:
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"


def comment_statements(db: str, tables: dict[str, tuple[str, dict[str, str]]]) -> list[str]:
    out: list[str] = []
    for table, (comment, columns) in tables.items():
        out.append(f"ALTER TABLE {db}.{table} MODIFY COMMENT {_quote(comment)}")
        if not columns:  # a table whose columns are another's (described there)
            continue
        out.append(
            f"ALTER TABLE {db}.{table} "
            + ", ".join(
                f"COMMENT COLUMN {column} {_quote(text)}" for column, text in columns.items()
            )
        )
    return out


def statements(db: str) -> tuple[str, ...]:
    """Migration 7: the comments of the tables it knew, and the views."""
    return (*comment_statements(db, TABLE_COMMENTS), *view_statements(db, VIEWS))


def view_statements(db: str, views: dict[str, tuple[str, str, dict[str, str]]]) -> tuple[str, ...]:
    """The views (re)created, each with its comment (migration 7's; later ones add theirs)."""
    return tuple(
        f"CREATE OR REPLACE VIEW {db}.{view} AS {select.format(db=db)} COMMENT {_quote(comment)}"
        for view, (comment, select, _columns) in views.items()
    )


def reference_markdown() -> str:
    """The reference part of docs/analysts.md (a test keeps the guide equal to it; after a
    schema change: `python -m mapservice.adapters.clickhouse.analyst_schema` prints it)."""
    out = ["### Views (start here)", ""]
    for view, (comment, _select, columns) in {**VIEWS, **LATER_VIEWS}.items():
        out += [f"#### `{view}`", "", comment, "", "| column | meaning |", "| --- | --- |"]
        out += [f"| `{c}` | {text} |" for c, text in columns.items()]
        out.append("")
    out += ["### Tables (storage)", ""]
    for table, (comment, columns) in {**TABLE_COMMENTS, **LATER_TABLE_COMMENTS}.items():
        out += [f"#### `{table}`", "", comment, "", "| column | meaning |", "| --- | --- |"]
        out += [f"| `{c}` | {text} |" for c, text in columns.items()]
        out.append("")
    return "\n".join(out).rstrip() + "\n"


if __name__ == "__main__":
    print(reference_markdown(), end="")
