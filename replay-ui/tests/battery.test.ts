import { describe, expect, it } from "vitest";
import { BatteryScales, levelPercent, scaleOfHighest } from "../src/lib/battery";
import { seriesOf } from "../src/lib/plots";
import type { TrackBucket, TrackBuckets } from "../src/lib/types";

/** A deterministic generator (mulberry32): the same cases on every run. */
function random(seed: number) {
  return () => {
    seed = (seed + 0x6d2b79f5) | 0;
    let t = Math.imul(seed ^ (seed >>> 15), 1 | seed);
    t = (t + Math.imul(t ^ (t >>> 7), 61 | t)) ^ t;
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

/** The levels the contracts allow on each scale, edges first: VDA 5050's batteryCharge and
 * the simulator's 2019 battery_level in percent (0..100), some 2019 robots a fraction. */
const EDGES = { percent: [0, 1, 1.5, 5, 99.5, 100], fraction: [0, 0.01, 0.5, 0.995, 1] };

/** A robot's levels: the edges of its scale and `n` more drawn across it, in random order;
 * a percent robot's history holds a level above 1 (a charged battery at some point). */
function history(scale: "percent" | "fraction", rnd: () => number, n: number): number[] {
  const top = scale === "percent" ? 100 : 1;
  const levels = [...EDGES[scale], ...Array.from({ length: n }, () => Math.round(rnd() * top * 1000) / 1000)];
  for (let i = levels.length - 1; i > 0; i--) {
    const j = Math.floor(rnd() * (i + 1));
    [levels[i], levels[j]] = [levels[j], levels[i]];
  }
  return levels;
}

const expected = (level: number, scale: "percent" | "fraction") => Math.round(scale === "fraction" ? level * 100 : level);

const bucketOf = (start_ms: number, levels: number[]): TrackBucket => ({
  start_ms, poses: levels.length, steps: levels.length - 1, distance_m: 0, step_ms: 0, speed_mps: null,
  first_ms: start_ms, last_ms: start_ms + 1, battery_min: Math.min(...levels), battery_max: Math.max(...levels),
  battery_mean: levels.reduce((a, b) => a + b, 0) / levels.length,
});

describe("battery scale, per robot", () => {
  it("reads every level of a robot on the robot's scale, whatever the sample (generated)", () => {
    const rnd = random(5050);
    for (let robot = 0; robot < 200; robot++) {
      const scale = robot % 2 ? "percent" : "fraction";
      const levels = history(scale, rnd, 1 + Math.floor(rnd() * 30));
      const scales = new BatteryScales();
      const id = `${scale}-${robot}`;
      scales.note(id, ...levels); // what the page read of it (its plots' buckets, its poses)
      expect(scales.scale(id)).toBe(scale);
      for (const level of levels) expect(scales.percent(id, level), `${id} at ${level}`).toBe(expected(level, scale));
      // Higher levels never read as lower percentages (a guess per sample broke this at 1 and 5).
      const shown = [...levels].sort((a, b) => a - b).map((l) => scales.percent(id, l)!);
      expect(shown).toEqual([...shown].sort((a, b) => a - b));
    }
  });

  it("draws a plot's battery on the robot's scale, the band around the mean (generated)", () => {
    const rnd = random(1);
    for (let robot = 0; robot < 100; robot++) {
      const scale = robot % 2 ? "percent" : "fraction";
      const levels = history(scale, rnd, 3 * (1 + Math.floor(rnd() * 20)));
      const buckets = Array.from({ length: Math.floor(levels.length / 3) }, (_, k) => bucketOf(k * 1000, levels.slice(3 * k, 3 * k + 3)));
      const answer: TrackBuckets = { robotId: `r${robot}`, from_ms: 0, to_ms: buckets.length * 1000, bucket_ms: 1000, distance_m: 0, buckets };
      const s = seriesOf(answer, new BatteryScales());
      buckets.forEach((b, k) => {
        expect(s.batteryMin[k]).toBe(expected(b.battery_min!, scale));
        expect(s.batteryMax[k]).toBe(expected(b.battery_max!, scale));
        expect(s.battery[k]).toBe(Math.round(scale === "fraction" ? b.battery_mean! * 100 : b.battery_mean!));
        expect(s.batteryMin[k]! <= s.battery[k]! && s.battery[k]! <= s.batteryMax[k]!).toBe(true);
      });
    }
  });

  it("shows the edge levels by the robot's scale: 5.0 of a percent robot is 5 %, 1 of a fraction robot 100 %", () => {
    const scales = new BatteryScales();
    scales.note("pct", 80);
    scales.note("frac", 0.9);
    expect([0, 1, 1.5, 5, 100].map((l) => scales.percent("pct", l))).toEqual([0, 1, 2, 5, 100]);
    expect([0, 0.5, 1].map((l) => scales.percent("frac", l))).toEqual([0, 50, 100]);
    // A robot that reports 1.5 or 5 reports percent from then on, whatever it sent before.
    expect(scales.percent("frac", 5)).toBe(5);
    expect(scales.percent("frac", 0.9)).toBe(1);
  });

  it("bounds levels the 2019 contract does not: below 0 and above 100, and nothing for non-numbers", () => {
    for (const scale of ["percent", "fraction"] as const) {
      expect(levelPercent(-3, scale)).toBe(0);
      expect(levelPercent(250, scale)).toBe(100);
      expect(levelPercent(null, scale)).toBeNull();
      expect(levelPercent(undefined, scale)).toBeNull();
      expect(levelPercent(Number.NaN, scale)).toBeNull();
    }
    expect(scaleOfHighest(null)).toBe("fraction");
    expect(scaleOfHighest(1)).toBe("fraction");
    expect(scaleOfHighest(1.0001)).toBe("percent");
  });

  it("asks the API once for a robot whose levels seen all lie within 0..1, and follows its answer", async () => {
    const asked: string[] = [];
    const highest: Record<string, number> = { low: 64, frac: 0.97 };
    const scales = new BatteryScales((id) => {
      asked.push(id);
      return Promise.resolve(highest[id]);
    });
    // A percent robot nearly empty (0.8 %) and a fraction robot at 80 % look alike at first.
    expect(scales.percent("low", 0.8)).toBe(80);
    expect(scales.percent("frac", 0.8)).toBe(80);
    expect(scales.percent("high", 40)).toBe(40); // above 1: nothing to ask
    scales.percent("low", 0.8);
    await Promise.resolve();
    await Promise.resolve();
    expect(asked).toEqual(["low", "frac"]);
    expect(scales.percent("low", 0.8)).toBe(1);
    expect(scales.percent("frac", 0.8)).toBe(80);
    expect(asked).toEqual(["low", "frac"]);
  });
});
