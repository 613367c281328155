import { describe, expect, it } from "vitest";
import { TRAIL_MAX_GAP_MS, TRAIL_MAX_REPLAY_SPEED, TRAIL_MAX_SPEED, trailRuns, trailShown, type TrailPoint } from "../src/lib/trail";

function random(seed: number) {
  return () => {
    seed = (seed * 1103515245 + 12345) % 2147483648;
    return seed / 2147483648;
  };
}

describe("the selected robot's trail", () => {
  it("never joins two points a robot could not have driven between, and keeps every drivable step", () => {
    for (let run = 0; run < 300; run++) {
      const rnd = random(run + 5);
      const points: TrailPoint[] = [];
      let t = 1_000_000;
      let x = 0;
      let y = 0;
      for (let i = 0; i < 120; i++) {
        t += rnd() < 0.05 ? TRAIL_MAX_GAP_MS + 1 + Math.floor(rnd() * 600_000) : 1000 + Math.floor(rnd() * 5000);
        if (rnd() < 0.05) [x, y] = [rnd() * 100 - 50, rnd() * 60 - 30]; // placed elsewhere
        else [x, y] = [x + (rnd() - 0.5) * 4, y + (rnd() - 0.5) * 4];
        points.push({ ts_ms: t, x, y });
      }
      const runs = trailRuns(points);
      const drivable = (p: TrailPoint, q: TrailPoint) =>
        q.ts_ms - p.ts_ms <= TRAIL_MAX_GAP_MS && Math.hypot(q.x - p.x, q.y - p.y) / ((q.ts_ms - p.ts_ms) / 1000) <= TRAIL_MAX_SPEED;
      const drawn = new Set<string>();
      for (const r of runs) {
        expect(r.length).toBeGreaterThan(1);
        for (let i = 1; i < r.length; i++) {
          expect(drivable(r[i - 1], r[i])).toBe(true);
          drawn.add(`${r[i - 1].ts_ms}>${r[i].ts_ms}`);
        }
      }
      for (let i = 1; i < points.length; i++) {
        expect(drawn.has(`${points[i - 1].ts_ms}>${points[i].ts_ms}`)).toBe(drivable(points[i - 1], points[i]));
      }
    }
  });

  it("is drawn paused, live and up to 60x, not while playing faster", () => {
    for (const speed of [1, 2, 4, 8, 60, 3600, 86400]) {
      expect(trailShown(false, false, speed)).toBe(true);
      expect(trailShown(true, true, speed)).toBe(true);
      expect(trailShown(true, false, speed)).toBe(speed <= TRAIL_MAX_REPLAY_SPEED);
    }
  });
});
