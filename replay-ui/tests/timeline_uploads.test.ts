import { describe, expect, it } from "vitest";
import { conflictSeek, stripMarks, uploadWritesPerBucket, withoutUploads, type UploadMark } from "../src/lib/timeline";
import type { Timeline } from "../src/lib/types";

function tl(counts: number[]): Timeline {
  return { from_ms: 0, to_ms: counts.length * 1000, bucket_ms: 1000,
    buckets: counts.map((c, i) => ({ start_ms: i * 1000, chunk_changes: c, conflicts: 0, robots_active: 1 })) };
}

describe("timeline without map uploads", () => {
  it("takes an upload's writes out of the bars, counting one crossing buckets from its writes", async () => {
    const t = tl([2, 190, 1, 30, 12]);
    const inOne: UploadMark = { ts_ms: 1000, end_ms: 1200, chunks: 187, robot_id: "map-upload" };
    const across: UploadMark = { ts_ms: 3500, end_ms: 4300, chunks: 35, robot_id: "r9" };
    const asked: UploadMark[] = [];
    const per = await uploadWritesPerBucket(t, [inOne, across], async (u) => {
      asked.push(u);
      return [...Array(25).fill(3600), ...Array(10).fill(4100)];
    });
    expect(asked).toEqual([across]); // one bucket: its chunks, no read
    expect([...per.entries()].sort()).toEqual([[1, 187], [3, 25], [4, 10]]);
    const fixed = withoutUploads(t, per);
    expect(fixed.buckets.map((b) => b.chunk_changes)).toEqual([2, 3, 1, 5, 2]);
    // The bars are scaled to the floor's changes, not to the upload's spike.
    const h = stripMarks(fixed, (x) => x / 10).map((m) => m.h);
    expect(h[3]).toBeCloseTo(36);
    expect(h[1]).toBeLessThan(36);
    expect(withoutUploads(t, new Map())).toBe(t);
  });

  it("seeks a conflict mark to just after its bucket's first conflict", () => {
    const cs = [{ ts_ms: 2500, seek_ms: 2501 }, { ts_ms: 2100, seek_ms: 2101 }, { ts_ms: 3100, seek_ms: 3101 }];
    expect(conflictSeek(cs, 2000, 1000)).toBe(2101);
    expect(conflictSeek(cs, 3000, 1000)).toBe(3101);
    expect(conflictSeek(cs, 0, 1000)).toBeNull();
  });
});
