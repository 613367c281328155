"""The allow-list itself: the committed file is what the rule makes of this engine's
system.functions, and the matching follows the engine's own name rules."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mapservice.sql.allow_list import (
    _CATALOGUE,
    NotAllowed,
    catalogue,
    catalogue_lines,
    check_identifiers,
    check_tree,
    parse_ast,
    quoted_identifiers,
)
from tests.fixtures.paths import ROOT


def test_the_committed_list_is_the_rule_applied_to_this_engine() -> None:
    """An engine upgrade changes system.functions; the list then says so here, and nothing
    is allowed by the upgrade alone (regenerate: python -m mapservice.sql.allow_list)."""
    pytest.importorskip("chdb")
    generated = subprocess.run(
        [sys.executable, "-m", "mapservice.sql.allow_list"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    ).stdout
    committed = _CATALOGUE.read_text()
    names = lambda text: [ln for ln in text.splitlines() if ln and not ln.startswith("#")]  # noqa: E731
    assert names(generated) == names(committed)


def test_the_rule_takes_categories_aliases_and_exclusions() -> None:
    rows = [
        ("sum", "Aggregate Functions", "", 1, 1),
        ("SUM_ALIAS", "", "sum", 1, 1),
        ("file", "Other", "", 0, 0),
        ("fileAlias", "", "file", 0, 0),
        ("toTypeName", "Other", "", 0, 0),
        ("serverTimezone", "Dates and Times", "", 0, 0),
        ("upper", "String", "", 1, 0),
    ]
    assert catalogue_lines(rows) == ["SUM_ALIAS\tia", "sum\tia", "toTypeName\t", "upper\ti"]


@pytest.mark.parametrize(
    "name,allowed",
    [
        ("count", True),
        ("COUNT", True),
        ("sumIf", True),
        ("uniqMergeState", True),
        ("groupArrayOrNull", True),
        ("quantilesTDigestIf", True),
        ("avgForEach", True),
        ("toString", True),
        ("TOSTRING", False),
        ("lambda", True),
        ("file", False),
        ("fileIf", False),
        ("dictGet", False),
        ("sleepIf", False),
        ("python", False),
    ],
)
def test_names_match_as_the_engine_matches_them(name, allowed) -> None:
    assert catalogue().allows(name) is allowed


def test_the_tree_is_read_by_indentation() -> None:
    ast = (
        "SelectWithUnionQuery (children 1)\n ExpressionList (children 1)\n"
        "  SelectQuery (children 2)\n   ExpressionList (children 1)\n"
        "    Function plus (alias p) (children 1)\n     ExpressionList (children 2)\n"
        "      Literal UInt64_1\n      Function file (children 1)\n"
        "   TablesInSelectQuery (children 1)\n"
    )
    tree = parse_ast(ast)
    select = tree.children[0].children[0]
    assert [c.kind for c in select.children] == ["ExpressionList", "TablesInSelectQuery"]
    assert select.children[0].children[0].words == ["plus"]
    with pytest.raises(NotAllowed, match="Function file is not allowed"):
        check_tree(tree, "mapservice")


def test_identifiers_with_line_breaks_are_found_outside_string_literals() -> None:
    """EXPLAIN AST prints identifiers raw, so a line break in one is refused; the same
    characters inside a string literal are data."""
    canonical = "SELECT 1 AS `a\\nb`, 'it''s `x\\ny`', `c\\`d` FROM `t`"
    assert quoted_identifiers(canonical) == ["a\\nb", "c\\`d", "t"]
    with pytest.raises(NotAllowed, match="line break"):
        check_identifiers(canonical)
    check_identifiers("SELECT 'a`\\n`b' AS s FROM `t`")


def test_every_top_level_line_of_the_dump_is_checked() -> None:
    """Lines after a stray top-level line are still nodes of the tree that is checked."""
    tree = parse_ast(
        "SelectWithUnionQuery (children 1)\n Literal UInt64_1 (alias a\nb)\n"
        "    Function file (children 1)\n"
    )
    with pytest.raises(NotAllowed, match="Function file"):
        check_tree(tree, "mapservice")
