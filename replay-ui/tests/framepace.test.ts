import { describe, expect, it } from "vitest";
import { framePace, IDLE_TICK_MS, LIVE_READOUT_MS, liveReadout, type PaceState } from "../src/lib/framepace";

/** Every combination of what the loop is told. */
function states(): PaceState[] {
  const out: PaceState[] = [];
  for (let i = 0; i < 16; i++) {
    out.push({ playback: !!(i & 1), seeking: !!(i & 2), settled: !!(i & 4), dirty: !!(i & 8) });
  }
  return out;
}

describe("framePace", () => {
  const walls = [0, 1, 499, 999, 1000, 1_764_500_000_001, 1_764_500_000_999, 1_764_500_001_000];

  it("asks for frames exactly while something moves by itself", () => {
    for (const s of states()) {
      for (const live of [false, true]) {
        for (const wall of walls) {
          const moving = s.playback || s.dirty || (!s.seeking && !s.settled);
          expect(framePace(s, wall, live) === "frame", JSON.stringify({ s, live, wall })).toBe(moving);
        }
      }
    }
  });

  it("at rest: paused an idle tick a second; live at the next wall second, when the clock's readout changes", () => {
    const rest = states().filter((s) => !s.playback && !s.dirty && (s.seeking || s.settled));
    expect(rest.length).toBeGreaterThan(0);
    for (const s of rest) {
      for (const wall of walls) {
        expect(framePace(s, wall, false)).toBe(IDLE_TICK_MS);
        const due = framePace(s, wall, true) as number;
        expect(due).toBeGreaterThan(0);
        expect(due).toBeLessThanOrEqual(LIVE_READOUT_MS);
        expect((wall + due) % LIVE_READOUT_MS).toBe(0);
      }
    }
  });

  it("the live readout is the playhead's wall second", () => {
    for (const t of walls) {
      const r = liveReadout(t);
      expect(r % LIVE_READOUT_MS).toBe(0);
      expect(t - r).toBeGreaterThanOrEqual(0);
      expect(t - r).toBeLessThan(LIVE_READOUT_MS);
    }
  });
});
