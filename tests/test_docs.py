"""The README and the reference pages in docs/ hold together: the configuration page lists
exactly the settings, every relative link (and #anchor) resolves, the README links every
page of docs/, and the README stays a newcomer's page."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mapservice.settings import Settings
from tests.fixtures.paths import DOCS, README, ROOT

PAGES = [README, *sorted(DOCS.glob("*.md"))]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
README_MAX_LINES = 300


def test_configuration_table_lists_every_setting():
    """Every MAPSERVICE_* setting appears in docs/configuration.md's table, and nothing else does."""
    text = (DOCS / "configuration.md").read_text()
    documented = set(re.findall(r"^\| `(MAPSERVICE_[A-Z0-9_]+)` \|", text, re.M))
    expected = {f"MAPSERVICE_{name.upper()}" for name in Settings.model_fields}
    assert documented == expected


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower().replace("`", ""))
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return {slug(m) for m in re.findall(r"^#+ (.+)$", text, re.M)}


def links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return [t for t in LINK.findall(text) if not re.match(r"[a-z]+:", t)]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page: Path):
    broken = []
    for target in links(page):
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.exists():
            broken.append(f"{target}: no such file")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target}: no heading #{anchor} in {resolved.relative_to(ROOT)}")
    assert not broken, f"{page.relative_to(ROOT)} links to what is not there:\n" + "\n".join(broken)


def test_the_readme_links_every_reference_page():
    linked = {(ROOT / t.partition("#")[0]).resolve() for t in links(README)}
    unlinked = [p.name for p in DOCS.glob("*.md") if p.resolve() not in linked]
    assert not unlinked, f"docs/ pages the README does not link: {unlinked}"


def test_the_readme_stays_a_newcomers_page():
    lines = README.read_text().count("\n")
    assert lines <= README_MAX_LINES, (
        f"README.md has {lines} lines: move reference material to a page in docs/ and link it"
    )
