import { describe, expect, it } from "vitest";
import { alignSeries, plotStepMs, plotWindow, seriesOf } from "../src/lib/plots";

const p = (ts_ms: number, x: number, y: number, battery_level: number | null) => ({ ts_ms, x, y, battery_level });

describe("plot series", () => {
  it("battery in %, speed over each step, distance driven since the window's start", () => {
    const s = seriesOf([p(0, 0, 0, 80), p(2000, 3, 4, 0.79), p(4000, 3, 4, null)], 2000);
    expect(s.ts).toEqual([0, 2000, 4000]);
    expect(s.battery).toEqual([80, 79, null]);
    expect(s.speed).toEqual([null, 2.5, 0]);
    expect(s.distance).toEqual([0, 5, 5]);
  });

  it("no speed across a silence (a gap of more than three steps), the distance still adds up", () => {
    const s = seriesOf([p(0, 0, 0, 50), p(60_000, 6, 8, 50)], 1000);
    expect(s.speed).toEqual([null, null]);
    expect(s.distance).toEqual([0, 10]);
  });

  it("puts several robots on one time axis, undefined where a robot has no sample (bridged, not a gap)", () => {
    const a = seriesOf([p(0, 0, 0, 10), p(2000, 0, 0, 20)], 1000);
    const b = seriesOf([p(1000, 0, 0, 30)], 1000);
    expect(alignSeries([a, b], "battery")).toEqual([[0, 1000, 2000], [10, undefined, 20], [undefined, 30, undefined]]);
  });

  it("a sample about every two pixels, at least a second apart, in whole seconds", () => {
    expect(plotStepMs(0, 3_600_000, 1200)).toBe(6000);
    expect(plotStepMs(0, 60_000, 1200)).toBe(1000);
    expect(plotStepMs(0, 7 * 86_400_000, 1000) % 1000).toBe(0);
  });

  it("a step of whole minutes from a whole minute over long spans (read from the pose keyframes)", () => {
    const from = Date.UTC(2026, 10, 20, 10, 0, 42, 5);
    const w = plotWindow(from, from + 7 * 86_400_000, 1000);
    expect(w.stepMs).toBe(1_260_000);
    expect(w.from).toBe(Date.UTC(2026, 10, 20, 10, 0));
    expect(plotWindow(from, from + 3_600_000, 1200)).toEqual({ from: Math.floor(from), stepMs: 6000 });
  });
});
