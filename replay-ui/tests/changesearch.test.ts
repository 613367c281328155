import { describe, expect, it } from "vitest";
import {
  changeSearchRanges, findNeighbourChange, neighbourChange, type Change, type ChangePage, type ChangePageReader, type WriteDensity,
} from "../src/lib/changefeed";

function random(seed: number) {
  return () => {
    seed = (seed * 1103515245 + 12345) % 2147483648;
    return seed / 2147483648;
  };
}

function change(ts: number): Change {
  return { kind: "change", ts_ms: ts, row: ts % 7, column: ts % 5, robot_id: "r", content_hash: "h", previous_hash: null, chunks: 1, end_ms: ts };
}

/** The change feed as the API serves it: [from, to), newest first, `limit` a page, `next` the cursor. */
function feed(changes: Change[], limit: number, reads: [number, number][]): ChangePageReader {
  const newest = [...changes].sort((a, b) => b.ts_ms - a.ts_ms);
  return async (from, to, before) => {
    reads.push([from, to]);
    const inWindow = newest.filter((c) => c.ts_ms >= from && c.ts_ms < to);
    const start = before ? Number(before) : 0;
    const page = inWindow.slice(start, start + limit);
    const next = start + limit < inWindow.length ? String(start + limit) : null;
    return { from_ms: from, to_ms: to, upload_rule: "", changes: page, next } as ChangePage;
  };
}

/** The timeline's buckets over [from, to): every change is a write; other writes changed nothing. */
function density(from: number, to: number, buckets: number, writes: number[]): WriteDensity {
  const bucketMs = Math.ceil((to - from) / buckets);
  const counts = new Array(buckets).fill(0);
  for (const t of writes) if (t >= from && t < to) counts[Math.floor((t - from) / bucketMs)]++;
  return { from_ms: from, to_ms: from + buckets * bucketMs, bucket_ms: bucketMs, buckets: counts.map((n, i) => ({ start_ms: from + i * bucketMs, chunk_changes: n })) };
}

describe("the previous/next change from the timeline's own counts", () => {
  it("finds what a full list of the span's changes gives, whatever the span, playhead, counts and page size", async () => {
    for (let run = 0; run < 400; run++) {
      const rnd = random(run + 17);
      const from = 1_000_000 + Math.floor(rnd() * 1e6);
      const to = from + 1000 + Math.floor(rnd() * 1e7);
      const n = Math.floor(rnd() * rnd() * 300);
      // Changes clustered or spread, some at the span's very ends, and writes that changed nothing.
      const ts = new Set<number>();
      for (let i = 0; i < n; i++) ts.add(from + Math.floor((rnd() < 0.5 ? rnd() * rnd() : rnd()) * (to - from)));
      if (rnd() < 0.2) ts.add(from);
      if (rnd() < 0.2) ts.add(to - 1);
      const changes = [...ts].map(change);
      const idle = Array.from({ length: Math.floor(rnd() * 50) }, () => from + Math.floor(rnd() * (to - from)));
      const tl = rnd() < 0.1 ? null : density(from, to, 1 + Math.floor(rnd() * 400), [...ts, ...idle]);
      const limit = 1 + Math.floor(rnd() * 30);
      for (let k = 0; k < 6; k++) {
        const playhead = k < changes.length && rnd() < 0.4 ? changes[k].ts_ms + Math.floor(rnd() * 3) - 1 : from + Math.floor(rnd() * (to - from + 1));
        for (const dir of [1, -1] as const) {
          const reads: [number, number][] = [];
          const ranges = changeSearchRanges(tl, [from, to], playhead, dir);
          const got = await findNeighbourChange(feed(changes, limit, reads), ranges, playhead, dir);
          const want = neighbourChange(changes, playhead, dir);
          expect(got?.ts_ms ?? null, `run ${run} playhead ${playhead} dir ${dir}`).toBe(want?.ts_ms ?? null);
          // Nothing read outside the span.
          for (const [a, b] of reads) expect(a >= from && b <= to && a < b).toBe(true);
        }
      }
    }
  });

  it("reads only the nearest bucket with writes when it holds a change", async () => {
    const from = 0;
    const to = 100_000;
    const changes = [change(20_500), change(40_100), change(80_000)];
    const tl = density(from, to, 100, changes.map((c) => c.ts_ms));
    const reads: [number, number][] = [];
    const next = await findNeighbourChange(feed(changes, 100, reads), changeSearchRanges(tl, [from, to], 30_000, 1), 30_000, 1);
    expect(next?.ts_ms).toBe(40_100);
    expect(reads).toEqual([[30_000, 41_000]]);
    reads.length = 0;
    const prev = await findNeighbourChange(feed(changes, 100, reads), changeSearchRanges(tl, [from, to], 30_000, -1), 30_000, -1);
    expect(prev?.ts_ms).toBe(20_500);
    expect(reads).toEqual([[20_000, 29_999]]);
  });

  it("reads nothing where the timeline counts no write on that side of the playhead", () => {
    const tl = density(0, 100_000, 100, [10_000]);
    expect(changeSearchRanges(tl, [0, 100_000], 50_000, 1)).toEqual([]);
    expect(changeSearchRanges(tl, [0, 100_000], 5_000, -1)).toEqual([]);
  });
});
