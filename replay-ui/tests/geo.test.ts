import { describe, expect, it } from "vitest";
import { chunkAt, metresToPixel, pixelToMetres, quaternionOfYaw, yawOf } from "../src/lib/geo";
import type { MapMeta } from "../src/lib/types";

const meta: MapMeta = {
  width: 400, height: 300, CHUNK_WIDTH: 100, CHUNK_HEIGHT: 100, CHUNK_ROWS: 3, CHUNK_COLS: 4,
  resolution: 0.05, origin: [-10, -5, 0],
};

describe("geo", () => {
  it("puts the origin at the bottom-left corner of the image", () => {
    expect(metresToPixel(meta, -10, -5)).toEqual({ col: 0, row: 300 });
    expect(metresToPixel(meta, -10 + 400 * 0.05, -5 + 300 * 0.05)).toEqual({ col: 400, row: 0 });
  });

  it("round-trips metres through pixels", () => {
    const p = metresToPixel(meta, 1.234, 2.5);
    const m = pixelToMetres(meta, p);
    expect(m.x).toBeCloseTo(1.234, 9);
    expect(m.y).toBeCloseTo(2.5, 9);
  });

  it("finds the chunk under a point, rows counted from the top", () => {
    expect(chunkAt(meta, -10 + 0.01, -5 + 0.01)).toEqual({ row: 2, column: 0 });
    expect(chunkAt(meta, -10 + 5.01, -5 + 14.99)).toEqual({ row: 0, column: 1 });
    expect(chunkAt(meta, -11, 0)).toBeNull();
  });

  it("reads the heading of a quaternion", () => {
    for (const yaw of [0, 0.5, -2, 3]) expect(yawOf(quaternionOfYaw(yaw))).toBeCloseTo(yaw, 9);
  });
});
