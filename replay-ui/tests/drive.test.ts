import { describe, expect, it } from "vitest";
import { blockedAt, blockedText, nearestFree, tryMove, type Floor } from "../src/lib/drive";
import type { MapMeta } from "../src/lib/types";

// 200 x 100 px at 5 cm (10 m x 5 m), origin (0, 0): free floor with a one-pixel-thin rack
// (black) along column 100 (x = 5.00-5.05 m) from row 20 to 80 (y = 1-4 m).
const meta: MapMeta = {
  width: 200, height: 100, CHUNK_WIDTH: 100, CHUNK_HEIGHT: 100, CHUNK_ROWS: 1, CHUNK_COLS: 2,
  resolution: 0.05, origin: [0, 0, 0],
};

function floor(): Floor {
  const grey = new Uint8Array(200 * 100).fill(254);
  for (let row = 20; row < 80; row++) grey[row * 200 + 100] = 0;
  return { width: 200, height: 100, grey };
}

describe("drive", () => {
  it("stops at a thin rack that a 0.5 m step would jump over", () => {
    const f = floor();
    expect(blockedAt(meta, f, 4.5, 2.5)).toBeNull();
    // From x 4.5 to 5.0 the disc (0.25 m) reaches x 5.0: stopped, position kept.
    const m = tryMove(meta, f, 4.5, 2.5, 5.0, 2.5);
    expect(m).toMatchObject({ x: 4.5, y: 2.5, blocked: { kind: "occupied", col: 100 } });
    expect(blockedText(m.blocked!, meta)).toMatch(/^stopped: occupied floor at x 5\.03 m, y 2\.\d\d m$/);
    // One step of 1 m right over the rack: also stopped (checked pixel by pixel).
    expect(tryMove(meta, f, 4.0, 2.5, 6.0, 2.5).blocked?.kind).toBe("occupied");
    // Around its end, below y = 1 m minus the radius, the way is free.
    expect(tryMove(meta, f, 4.5, 0.5, 5.5, 0.5).blocked).toBeNull();
  });

  it("never leaves the map", () => {
    expect(tryMove(meta, floor(), 0.5, 2.5, 0.0, 2.5)).toEqual({ x: 0.5, y: 2.5, blocked: { kind: "edge" } });
    expect(tryMove(meta, null, 9.5, 4.5, 9.5, 5.0).blocked).toEqual({ kind: "edge" });
    expect(blockedText({ kind: "edge" }, meta)).toBe("stopped: the map's edge");
  });

  it("lets a robot standing on occupied floor drive off it, but not off the map", () => {
    const f = floor();
    f.grey.fill(0, 40 * 200, 60 * 200); // rows 40-59 painted black under the robot at y 2.5 m
    expect(blockedAt(meta, f, 2.0, 2.5)?.kind).toBe("occupied");
    expect(tryMove(meta, f, 2.0, 2.5, 2.0, 3.0).blocked).toBeNull();
  });

  it("starts the robot on free floor next to where it is asked to", () => {
    const f = floor();
    expect(nearestFree(meta, f, 5.0, 2.5, 0.5)).not.toEqual({ x: 5.0, y: 2.5 });
    const p = nearestFree(meta, f, 5.0, 2.5, 0.5);
    expect(blockedAt(meta, f, p.x, p.y)).toBeNull();
    expect(Math.abs(p.x - 5.0)).toBe(0.5);
  });
});
