import { describe, expect, it } from "vitest";
import { EventBuffer, chunkStepMs, complete, fetchSpanMs, lookaheadMs, poseStepMs, type Source } from "../src/lib/buffer";
import { SPEEDS } from "../src/lib/clock";
import { cellKey, compareChanges, MapState } from "../src/lib/mapstate";
import type { ChunkCell, ChunkChange, EventWindow, Pose } from "../src/lib/types";

function history(n: number, span: number): ChunkChange[] {
  const out: ChunkChange[] = [];
  for (let i = 0; i < n; i++) {
    out.push({ ts_ms: Math.floor((i * span) / n), row: i % 3, column: (i * 7) % 5, robotId: `r${i % 2}`, content_hash: `h${i}` });
  }
  return out.sort(compareChanges);
}

/** The server's compaction: per cell and absolute bucket, the greatest (ts, robot) write. */
function compactWrites(writes: ChunkChange[], step: number): ChunkChange[] {
  const won = new Map<string, ChunkChange>();
  for (const c of writes) {
    const k = `${c.row}:${c.column}:${Math.floor(c.ts_ms / step)}`;
    const cur = won.get(k);
    if (!cur || compareChanges(c, cur) >= 0) won.set(k, c);
  }
  return [...won.values()].sort(compareChanges);
}

function fakeSource(all: ChunkChange[], limit = Infinity): Source & { calls: [number, number][]; chunkSteps: number[] } {
  const calls: [number, number][] = [];
  const chunkSteps: number[] = [];
  const mapAt = async (t: number): Promise<ChunkCell[]> => {
    const best = new Map<number, ChunkCell>();
    for (const c of all) if (c.ts_ms <= t) best.set(cellKey(c.row, c.column), c);
    return [...best.values()].map((c) => ({ ...c }));
  };
  return {
    calls,
    chunkSteps,
    async events(f: number, t: number, step: number, chunkStep = 0): Promise<EventWindow> {
      calls.push([f, t]);
      chunkSteps.push(chunkStep);
      let inside = all.filter((c) => c.ts_ms >= f && c.ts_ms < t).map((c) => ({ ...c }));
      if (chunkStep > 0) inside = compactWrites(inside, chunkStep);
      const poses: Pose[] = [];
      return { from_ms: f, to_ms: t, step_ms: step, chunks: inside.slice(0, limit), poses, truncated: inside.length > limit };
    },
    mapAt,
    robotsAt: async () => [],
  };
}

async function fill(b: EventBuffer, playhead: number, dir: 1 | -1, speed: number, now: number) {
  for (let i = 0; i < 1000; i++) {
    const p = b.ensure(playhead, dir, speed, now, 0);
    if (!p) return;
    await p;
  }
}

describe("buffer sizing", () => {
  it("looks further ahead and fetches bigger spans at higher speed", () => {
    for (let i = 1; i < SPEEDS.length; i++) {
      expect(lookaheadMs(SPEEDS[i])).toBeGreaterThanOrEqual(lookaheadMs(SPEEDS[i - 1]));
      expect(fetchSpanMs(SPEEDS[i])).toBeGreaterThanOrEqual(fetchSpanMs(SPEEDS[i - 1]));
    }
    expect(lookaheadMs(86400)).toBeGreaterThan(3_600_000);
    expect(poseStepMs(8)).toBe(0);
    expect(poseStepMs(86400)).toBeGreaterThan(60_000);
  });
});

describe("EventBuffer", () => {
  it("keeps the look-ahead ahead of the playhead and no further than now", async () => {
    const all = history(500, 100_000);
    const src = fakeSource(all);
    const b = new EventBuffer(src, 10_000, 8);
    b.reset(10_000, 8, []);
    await fill(b, 10_000, 1, 8, 50_000);
    expect(b.covers(10_000, 10_000 + lookaheadMs(8))).toBe(true);
    expect(b.to).toBeLessThanOrEqual(50_001);
    expect(b.chunks).toEqual(all.filter((c) => c.ts_ms > 10_000 && c.ts_ms < b.to));
  });

  it("continues after a truncated window without losing writes", async () => {
    const all = history(300, 30_000);
    const src = fakeSource(all, 17);
    const b = new EventBuffer(src, 0, 1);
    b.reset(-1, 1, []);
    for (let i = 0; i < 200 && b.to < 30_000; i++) await b.extendForward(b.to, b.to + 30_000);
    expect(b.chunks.map((c) => c.content_hash)).toEqual(all.map((c) => c.content_hash));
  });

  it("plays backwards across a fetched span with exact previous states", async () => {
    const all = history(600, 60_000);
    const src = fakeSource(all);
    const start = 50_000;
    const b = new EventBuffer(src, start, 60);
    b.reset(start, 60, []);
    const s = new MapState();
    s.reset(await src.mapAt(start));
    await fill(b, start, -1, 60, 60_000);
    expect(b.from).toBeLessThanOrEqual(start - 20_000);
    s.move(b.chunks, start, 5_000);
    const expected = await src.mapAt(5_000);
    expect(new Map([...s.cells].map(([k, c]) => [k, c.content_hash]))).toEqual(
      new Map(expected.map((c) => [cellKey(c.row, c.column), c.content_hash])));
  });

  it("takes a window of 200,000 writes (more than a function call's arguments)", async () => {
    const all = history(200_000, 7_200_000);
    const b = new EventBuffer(fakeSource(all), 0, 3600);
    b.compact = false;
    b.reset(0, 3600, []);
    await b.extendForward(1, 7_200_001);
    expect(b.chunks.length).toBe(all.length - 1); // all but the write at 0, before the window
    expect(b.to).toBe(7_200_001);
  });

  it("trims behind the playhead", async () => {
    const all = history(500, 100_000);
    const b = new EventBuffer(fakeSource(all), 0, 8);
    b.reset(0, 8, []);
    await b.extendForward(1, 80_000);
    b.trim(60_000, 1, 10_000);
    expect(b.from).toBe(50_000);
    expect(b.chunks[0].ts_ms).toBeGreaterThanOrEqual(50_000);
  });

  it("treats a truncated window as complete only before its last instant", () => {
    const w: EventWindow = {
      from_ms: 0, to_ms: 100, step_ms: 0, truncated: true, poses: [],
      chunks: [10, 20, 20].map((ts, i) => ({ ts_ms: ts, row: 0, column: i, robotId: "r", content_hash: `${i}` })),
    };
    const c = complete(w, 0, 100);
    expect(c.to).toBe(20);
    expect(c.chunks).toHaveLength(1);
    const cut = complete({ ...w, to_ms: 20, chunks: w.chunks.slice(0, 1) }, 0, 100);
    expect(cut.to).toBe(20);
  });

  it("asks for whole-minute pose steps and whole-minute window starts after the first", async () => {
    expect(poseStepMs(3600) % 60_000).toBe(0);
    expect(poseStepMs(86400) % 60_000).toBe(0);
    const src = fakeSource(history(10, 1_000_000));
    const b = new EventBuffer(src, 12_345, 3600);
    b.reset(12_345, 3600, []);
    await fill(b, 12_345, 1, 3600, 10_000_000);
    expect(src.calls.slice(1).every(([f]) => f % 60_000 === 0)).toBe(true);
  });
});

describe("EventBuffer above 60x (compacted writes)", () => {
  const MIN = 60_000;
  const hashes = (s: MapState) => new Map([...s.cells].map(([k, c]) => [k, c.content_hash]));
  const exact = async (src: Source, t: number) =>
    new Map((await src.mapAt(t)).map((c) => [cellKey(c.row, c.column), c.content_hash]));

  it("compacts only above 60x, in buckets of whole minutes no longer than a frame's worth of data", () => {
    expect([1, 8, 60].map(chunkStepMs)).toEqual([0, 0, 0]);
    expect(chunkStepMs(3600)).toBe(MIN);
    expect(chunkStepMs(86400)).toBe(20 * MIN);
    for (const speed of [3600, 86400]) {
      expect(chunkStepMs(speed)).toBeLessThanOrEqual(Math.max(MIN, (speed * 1000) / 60));
      expect(86_400_000 % chunkStepMs(speed)).toBe(0);
    }
    expect(fetchSpanMs(86400)).toBe(86_400_000); // the API's longest window
  });

  it("ends windows on whole buckets and shows the exact map at every bucket boundary", async () => {
    const all = history(3000, 6 * 3_600_000);
    const src = fakeSource(all);
    const start = 12_345;
    const b = new EventBuffer(src, start, 86400);
    b.reset(start, 86400, []);
    expect(b.chunkStepMs).toBe(20 * MIN);
    const s = new MapState();
    s.reset(await src.mapAt(start));
    await fill(b, start, 1, 86400, 3 * 86_400_000);
    expect(src.chunkSteps.every((x) => x === 20 * MIN)).toBe(true);
    expect(src.calls.every(([, t]) => t % (20 * MIN) === 0)).toBe(true);
    expect(src.calls.every(([f, t]) => t - f <= 86_400_000)).toBe(true); // the API's longest window
    expect(b.chunks.length).toBeLessThan(all.length / 3);
    let at = start;
    for (let edge = 20 * MIN; edge <= 6 * 3_600_000; edge += 20 * MIN) {
      s.move(b.chunks, at, edge - 1);
      at = edge - 1;
      expect(hashes(s)).toEqual(await exact(src, edge - 1));
    }
    expect(s.applied).toBe(b.chunks.filter((c) => c.ts_ms <= at).length);
  });

  it("plays backwards through compacted windows, exact at every bucket boundary", async () => {
    const all = history(3000, 6 * 3_600_000);
    const src = fakeSource(all);
    const start = 5 * 3_600_000 + 777;
    const b = new EventBuffer(src, start, 3600);
    b.reset(start, 3600, []);
    const s = new MapState();
    s.reset(await src.mapAt(start));
    await fill(b, start, -1, 3600, 10 * 3_600_000);
    expect(b.from).toBeLessThanOrEqual(start - lookaheadMs(3600));
    let at = start;
    for (let edge = Math.floor(start / MIN) * MIN; edge > b.from; edge -= 7 * MIN) {
      s.move(b.chunks, at, edge - 1);
      at = edge - 1;
      expect(hashes(s)).toEqual(await exact(src, edge - 1));
    }
  });

  it("asks for every write at any speed once compaction is switched off", async () => {
    const src = fakeSource(history(100, 3_600_000));
    const b = new EventBuffer(src, 0, 86400);
    b.compact = false;
    b.reset(0, 86400, []);
    await b.ensure(0, 1, 86400, 10 * 3_600_000, 0);
    expect(b.chunkStepMs).toBe(0);
    expect(src.chunkSteps).toEqual([0]);
    // Every write: windows of 6 h (to the next whole minute), as before compaction.
    expect(src.calls[0][1]).toBe(6 * 3_600_000 + 60_000);
  });
});

describe("EventBuffer near now", () => {
  it("does not poll tiny windows while the playhead has data ahead", async () => {
    const src = fakeSource(history(10, 100_000));
    const b = new EventBuffer(src, 90_000, 1);
    b.reset(90_000, 1, []);
    await fill(b, 90_000, 1, 1, 95_000);
    const calls = src.calls.length;
    expect(b.ensure(90_500, 1, 1, 95_500, 0)).toBeNull();
    expect(src.calls.length).toBe(calls);
    expect(b.ensure(94_500, 1, 1, 95_500, 0)).not.toBeNull();
  });
});
