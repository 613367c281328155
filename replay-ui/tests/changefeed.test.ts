import { describe, expect, it } from "vitest";
import { boxOfPixels, changesUrl, neighbourChange, seekTargetOf, type Change } from "../src/lib/changefeed";
import type { MapMeta } from "../src/lib/types";

const meta = { width: 500, height: 400, CHUNK_WIDTH: 100, CHUNK_HEIGHT: 100, CHUNK_ROWS: 4, CHUNK_COLS: 5 } as MapMeta;

function change(ts: number, kind: "change" | "upload" = "change", end = ts): Change {
  return { kind, ts_ms: ts, row: 0, column: 0, robot_id: "r", content_hash: "h", previous_hash: null, chunks: 1, end_ms: end };
}

describe("change feed", () => {
  it("asks for the span, robot, box and page", () => {
    const url = changesUrl("", 1000.4, 2000.2, { robot: "r 1", box: { rowMin: 1, rowMax: 2, colMin: 0, colMax: 3 } }, 50, "5:1:1:r");
    const q = new URL(url, "http://x").searchParams;
    expect(Object.fromEntries(q)).toEqual({ from: "1000", to: "2001", limit: "50", robot: "r 1", row_min: "1", row_max: "2", col_min: "0", col_max: "3", before: "5:1:1:r" });
    expect(changesUrl("", 0, 1, { robot: null, box: null })).toBe("/api/v1/changes?from=0&to=1&limit=200");
  });

  it("turns a drawn rectangle into the chunks it touches, clipped to the grid", () => {
    expect(boxOfPixels(meta, { row: 250, col: 420 }, { row: 50, col: 120 })).toEqual({ rowMin: 0, rowMax: 2, colMin: 1, colMax: 4 });
    expect(boxOfPixels(meta, { row: -50, col: -10 }, { row: 900, col: 900 })).toEqual({ rowMin: 0, rowMax: 3, colMin: 0, colMax: 4 });
    expect(boxOfPixels(meta, { row: 500, col: 10 }, { row: 600, col: 20 })).toBeNull();
  });

  it("seeks just after a change, after an upload's last write", () => {
    expect(seekTargetOf(change(100))).toBe(101);
    expect(seekTargetOf(change(100, "upload", 900))).toBe(901);
  });

  it("steps to the next and previous change from the playhead, walking the list", () => {
    const cs = [change(300), change(100), change(200)];
    expect(neighbourChange(cs, 0, 1)?.ts_ms).toBe(100);
    expect(neighbourChange(cs, 101, 1)?.ts_ms).toBe(200);
    expect(neighbourChange(cs, 201, -1)?.ts_ms).toBe(100);
    expect(neighbourChange(cs, 301, 1)).toBeNull();
    expect(neighbourChange(cs, 101, -1)).toBeNull();
  });
});
