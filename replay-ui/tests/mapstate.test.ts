import { describe, expect, it } from "vitest";
import { annotatePrev, cellKey, compareChanges, MapState } from "../src/lib/mapstate";
import type { ChunkCell, ChunkChange } from "../src/lib/types";

function w(ts: number, row: number, column: number, hash: string, robot = "r1"): ChunkChange {
  return { ts_ms: ts, row, column, content_hash: hash, robotId: robot };
}

/** The server's rule, brute force: per cell the greatest (ts, robot) with ts <= t. */
function fold(all: ChunkCell[], t: number): Map<number, string> {
  const best = new Map<number, ChunkCell>();
  for (const c of all) {
    if (c.ts_ms > t) continue;
    const k = cellKey(c.row, c.column);
    const cur = best.get(k);
    if (!cur || compareChanges(c, cur) >= 0) best.set(k, c);
  }
  return new Map([...best].map(([k, c]) => [k, c.content_hash]));
}

function shown(s: MapState): Map<number, string> {
  return new Map([...s.cells].map(([k, c]) => [k, c.content_hash]));
}

function random(seed: number) {
  return () => {
    seed = (seed * 1103515245 + 12345) % 2147483648;
    return seed / 2147483648;
  };
}

describe("MapState", () => {
  it("applies every write between two frames in order and logs each", () => {
    const s = new MapState();
    s.reset([w(0, 0, 0, "a")]);
    const writes = [w(10, 0, 0, "b"), w(10, 0, 0, "c", "r2"), w(20, 1, 1, "d"), w(30, 0, 0, "e")];
    expect(s.move(writes, 0, 25)).toBe(3);
    expect(s.log.map((l) => l.content_hash)).toEqual(["b", "c", "d"]);
    expect(s.get(cellKey(0, 0))!.content_hash).toBe("c");
  });

  it("undoes writes backwards to the exact earlier state", () => {
    const s = new MapState();
    s.reset([w(0, 0, 0, "a")]);
    const writes = [w(10, 0, 0, "b"), w(20, 1, 1, "d"), w(30, 0, 0, "e")];
    s.move(writes, 0, 30);
    s.move(writes, 30, 15);
    expect(s.get(cellKey(0, 0))!.content_hash).toBe("b");
    expect(s.get(cellKey(1, 1))).toBeNull();
    expect(s.log.slice(-2).map((l) => [l.dir, l.ts_ms])).toEqual([[-1, 30], [-1, 20]]);
  });

  it("matches a brute-force fold at every frame, forwards and backwards, at random frame steps", () => {
    const rnd = random(7);
    const all: ChunkChange[] = [];
    for (let i = 0; i < 2000; i++) {
      all.push(w(Math.floor(rnd() * 10_000), Math.floor(rnd() * 4), Math.floor(rnd() * 4),
        `h${i}`, `r${Math.floor(rnd() * 3)}`));
    }
    all.sort(compareChanges);
    const start = 2_000;
    const s = new MapState();
    s.reset([...fold(all.filter((c) => c.ts_ms <= start), start)].map(([k, h]) => {
      const c = all.filter((x) => x.ts_ms <= start && cellKey(x.row, x.column) === k && x.content_hash === h)[0];
      return { ...c };
    }));
    const before = all.filter((c) => c.ts_ms <= start);
    const base = fold(before, start);
    const lookup = (k: number): ChunkCell | null => {
      const h = base.get(k);
      return h ? before.find((c) => c.content_hash === h)! : null;
    };
    const buffered = all.filter((c) => c.ts_ms > start).map((c) => ({ ...c }));
    annotatePrev(lookup, buffered);
    let t = start;
    for (let frame = 0; frame < 400; frame++) {
      const next = Math.max(start, Math.min(9_999, t + Math.floor((rnd() - 0.4) * 300)));
      s.move(buffered, t, next);
      t = next;
      expect(shown(s)).toEqual(fold(all, t));
    }
  });

  it("marks dirty on reset only the cells whose picture changed or went away", () => {
    const s = new MapState();
    s.reset([w(0, 0, 0, "a"), w(0, 0, 1, "b"), w(0, 0, 2, "c")]);
    expect(s.dirty.size).toBe(3);
    s.dirty.clear();
    s.reset([w(5, 0, 0, "a"), w(5, 0, 1, "x"), w(5, 1, 1, "y")]);
    expect([...s.dirty].sort((a, b) => a - b)).toEqual([cellKey(0, 1), cellKey(0, 2), cellKey(1, 1)]);
    expect(s.get(cellKey(0, 0))!.ts_ms).toBe(5);
    expect(s.get(cellKey(0, 2))).toBeNull();
  });

  it("keeps a late, older write out of the current state but still logs it", () => {
    const s = new MapState();
    s.reset([w(100, 0, 0, "new")]);
    s.applyForward([w(50, 0, 0, "old")]);
    expect(s.get(cellKey(0, 0))!.content_hash).toBe("new");
    expect(s.log).toHaveLength(1);
  });
});
