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


def test_the_webhook_verification_snippet_accepts_a_delivery_and_refuses_tampering():
    """docs/history.md's receiver snippet, run: it accepts a delivery signed as the
    processors sign it, and refuses another secret, a changed body, a moved or stale
    timestamp."""
    import time

    from mapservice.core.webhooks import signed_headers

    text = (DOCS / "history.md").read_text()
    block = text.split("<!-- verify-webhook -->", 1)[1].split("<!-- /verify-webhook -->", 1)[0]
    code = block.split("```python", 1)[1].split("```", 1)[0]
    scope: dict = {}
    exec(compile(code, "docs/history.md", "exec"), scope)
    verified = scope["verified"]
    secret, body, now = "0123456789abcdef-plant", b'{"kind": "stuck"}', int(time.time())
    headers = {k.lower(): v for k, v in signed_headers(secret, now, body).items()}
    assert verified(secret, headers, body)
    assert not verified(secret + "x", headers, body)
    assert not verified(secret, headers, body + b" ")
    assert not verified(secret, {**headers, "x-mapservice-timestamp": str(now + 1)}, body)
    stale = {k.lower(): v for k, v in signed_headers(secret, now - 301, body).items()}
    assert not verified(secret, stale, body)
