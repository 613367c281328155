import { describe, expect, it } from "vitest";
import { alignSeries, distanceText, drivenBetween, durationText, plotBuckets, seriesOf } from "../src/lib/plots";
import type { TrackBucket, TrackBuckets } from "../src/lib/types";

const bucket = (start_ms: number, distance_m: number, step_ms: number, battery: [number, number, number] | null): TrackBucket => ({
  start_ms, poses: 3, steps: 2, distance_m, step_ms, speed_mps: step_ms ? distance_m / (step_ms / 1000) : null,
  first_ms: start_ms, last_ms: start_ms + 1, battery_min: battery?.[0] ?? null, battery_max: battery?.[1] ?? null,
  battery_mean: battery?.[2] ?? null,
});
const answer = (from_ms: number, to_ms: number, bucket_ms: number, buckets: TrackBucket[]): TrackBuckets =>
  ({ robotId: "r", from_ms, to_ms, bucket_ms, distance_m: buckets.reduce((a, b) => a + b.distance_m, 0), buckets });

/** A deterministic generator (mulberry32): the same cases on every run. */
function random(seed: number) {
  return () => {
    seed = (seed + 0x6d2b79f5) | 0;
    let t = Math.imul(seed ^ (seed >>> 15), 1 | seed);
    t = (t + Math.imul(t ^ (t >>> 7), 61 | t)) ^ t;
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

describe("plot series", () => {
  it("battery in % with its range, speed over the steps' time, distance summed from the window's start", () => {
    const s = seriesOf(answer(500, 3500, 1000, [bucket(0, 3, 2000, [70, 80, 75]), bucket(2000, 5, 1000, [79, 80, 79.5])]));
    expect(s.mid).toEqual([750, 1500, 2500, 3250]); // buckets cut by the window's ends: their middle within it
    expect(s.edges).toEqual([500, 1000, 2000, 3000, 3500]);
    expect(s.battery).toEqual([75, null, 80, null]);
    expect(s.batteryMin).toEqual([70, null, 79, null]);
    expect(s.batteryMax).toEqual([80, null, 80, null]);
    expect(s.speed).toEqual([1.5, null, 5, null]);
    expect(s.bucketDistance).toEqual([3, 0, 5, 0]);
    expect(s.distance).toEqual([0, 3, 3, 8, 8]);
  });

  it("puts several robots on one time axis, each key at its own instants, undefined where one has none", () => {
    const a = seriesOf(answer(0, 2000, 1000, [bucket(0, 1, 1000, [10, 20, 15])]));
    const b = seriesOf(answer(1000, 2000, 1000, [bucket(1000, 2, 1000, null)]));
    expect(alignSeries([a, b], ["battery", "batteryMax"])).toEqual([[500, 1500], [15, null], [20, null], [undefined, null], [undefined, null]]);
    expect(alignSeries([a, b], ["distance"])).toEqual([[0, 1000, 2000], [0, 1, 1], [undefined, 0, 2]]);
  });

  it("a day's distance is the same from buckets of any size, and equals the sum of the steps in it", () => {
    const rnd = random(7);
    const DAY = 86_400_000;
    for (let k = 0; k < 20; k++) {
      // A raw track over three days: positions, with silent gaps; its steps credited where they end.
      const poses: { t: number; x: number }[] = [];
      for (let t = Math.floor(rnd() * 60_000); t < 3 * DAY; t += rnd() < 0.01 ? 3_600_000 * rnd() : 1000 + Math.floor(rnd() * 60_000)) {
        poses.push({ t: Math.floor(t), x: (poses.at(-1)?.x ?? 0) + rnd() * 10 });
      }
      const day = DAY;
      const inDay = poses.reduce((a, p, i) => a + (i && p.t >= day && p.t < 2 * DAY ? p.x - poses[i - 1].x : 0), 0);
      for (const size of [60_000, 300_000, 3_600_000, DAY]) {
        const by = new Map<number, number>();
        poses.forEach((p, i) => { if (i) by.set(Math.floor(p.t / size) * size, (by.get(Math.floor(p.t / size) * size) ?? 0) + p.x - poses[i - 1].x); });
        const s = seriesOf(answer(0, 3 * DAY, size, [...by].map(([start, d]) => bucket(start, d, 1000, null))));
        expect(drivenBetween(s, day, 2 * DAY)).toBeCloseTo(inDay, 6);
      }
    }
  });

  it("about a bucket every three pixels, within the API's cap", () => {
    expect(plotBuckets(1200)).toBe(400);
    expect(plotBuckets(1)).toBe(2);
    expect(plotBuckets(10_000)).toBe(1000);
  });

  it("names bucket sizes and distances as a person reads them", () => {
    expect([1000, 300_000, 3_600_000, 2 * 86_400_000, 1500].map(durationText)).toEqual(["1 s", "5 min", "1 h", "2 d", "1500 ms"]);
    expect([850.4, 12_346, 158_000].map(distanceText)).toEqual(["850 m", "12.35 km", "158.0 km"]);
  });
});
