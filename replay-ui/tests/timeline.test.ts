import { describe, expect, it } from "vitest";
import { BAR_MAX_PX, stripMarks } from "../src/lib/timeline";

const bucket = (start_ms: number, chunk_changes: number, conflicts: number, robots_active: number) =>
  ({ start_ms, chunk_changes, conflicts, robots_active });

describe("stripMarks", () => {
  const xOf = (t: number) => t / 10; // 10 ms a pixel
  const tl = {
    from_ms: 0, to_ms: 300, bucket_ms: 100,
    buckets: [bucket(0, 0, 0, 5), bucket(100, 4, 1, 2), bucket(200, 2, 0, 0)],
  };
  const marks = stripMarks(tl, xOf);

  it("bands every bucket where robots reported, map changes or not", () => {
    expect(marks.map((m) => m.active)).toEqual([true, true, false]);
  });

  it("scales change bars to the busiest bucket and keeps the conflict counts", () => {
    expect(marks.map((m) => m.h)).toEqual([0, BAR_MAX_PX, BAR_MAX_PX / 2]);
    expect(marks.map((m) => m.conflicts)).toEqual([0, 1, 0]);
  });

  it("places each bucket at its start, a hair narrower than its span", () => {
    expect(marks.map((m) => [m.x, m.w])).toEqual([[0, 9.5], [10, 9.5], [20, 9.5]]);
  });
});
