"""What the replay page must show after `mapservice bench ui` played it at a high speed,
asked of the API: the exact map at an instant, the chunk writes in a span at one
compaction step, and the page's rule for folding them (the skipped-change checks).
"""

from __future__ import annotations

DAY_MS = 86_400_000


def _get(api_url: str, path: str, **params):
    import httpx

    r = httpx.get(f"{api_url}{path}", params=params, timeout=600)
    r.raise_for_status()
    return r.json()


def api_map(api_url: str, at_ms: int) -> dict[tuple[int, int], tuple]:
    """The API's map at T: (row, column) -> (ts_ms, robotId, content_hash)."""
    doc = _get(api_url, "/api/v1/map", at=at_ms, layout="compact")
    i = [doc["fields"].index(f) for f in ("row", "column", "ts_ms", "robotId", "content_hash")]
    return {(c[i[0]], c[i[1]]): (c[i[2]], c[i[3]], c[i[4]]) for c in doc["cells"]}


def api_writes(api_url: str, f: int, t: int, step: int) -> list[dict]:
    """The API's chunk writes in [f, t) at one compaction step, over as many requests as the
    API's caps need (split on whole buckets, so no bucket is cut in two)."""
    out: list[dict] = []
    align = step or 60_000
    while f < t:
        end = min(t, (f + DAY_MS // 2) // align * align)
        end = end if end > f else min(t, f + DAY_MS // 2)
        doc = _get(
            api_url,
            "/api/v1/events",
            **{"from": f, "to": end, "step_ms": 3_600_000, "chunk_step_ms": step},
        )
        out.extend(doc["chunks"])
        f = doc["to_ms"] if doc["truncated"] else end
    return out


def fold(base: dict, writes: list[dict]) -> dict:
    """The page's rule: a write replaces the cell unless the cell shows a later one."""
    state = dict(base)
    for w in sorted(writes, key=lambda w: (w["ts_ms"], w["robotId"])):
        k = (w["row"], w["column"])
        if k not in state or (w["ts_ms"], w["robotId"]) >= state[k][:2]:
            state[k] = (w["ts_ms"], w["robotId"], w["content_hash"])
    return state


def expected_at(api_url: str, p0: int, p1: int, step: int) -> tuple[dict, list[dict]]:
    """What the page must show at p1 after playing from p0 (the map exact at p0), and the
    writes it must have applied (forwards) or undone (backwards) on the way, in the API's
    order.

    Every write (step 0): map_at(p1) and the writes between. Compacted: the buffer's windows
    end on whole buckets, so the page holds whole buckets [B, B+step) (cut only at p0 + 1,
    where its first window starts or ends); at p1 it shows the exact map before p1's bucket
    B plus that bucket's winners up to p1.
    """
    lo, hi = min(p0, p1), max(p0, p1)
    if step == 0:
        return api_map(api_url, p1), api_writes(api_url, lo + 1, hi + 1, 0)
    b = p1 // step * step
    if p1 > p0:
        start = max(b, p0 + 1)
        part = api_writes(api_url, start, b + step, step)
        whole = api_writes(api_url, p0 + 1, start, step) if start > p0 + 1 else []
        shown = [w for w in part if w["ts_ms"] <= p1]
        return fold(api_map(api_url, start - 1), shown), whole + shown
    top = min(b + step, p0 + 1)
    part = api_writes(api_url, b, top, step)
    above = api_writes(api_url, top, p0 + 1, step) if p0 + 1 > top else []
    shown = [w for w in part if w["ts_ms"] <= p1]
    return fold(api_map(api_url, b - 1), shown), [w for w in part if w["ts_ms"] > p1] + above


def mismatches(page_cells: list, expected: dict) -> int:
    page = {(c[0], c[1]): (c[2], c[3], c[4]) for c in page_cells}
    return sum(page.get(k) != expected.get(k) for k in page.keys() | expected.keys())
