import { describe, expect, it } from "vitest";
import { mayGrow, readAheadTo, REFRESH_MS, stillAnswers, type SpanRead } from "../src/lib/cadence";

describe("the refresh cadence", () => {
  it("reads a span that reaches now ahead past it, so its end sliding asks nothing until the next refresh", () => {
    const now = 1_800_000_000_000;
    for (let back = -60_000; back <= 3_600_000; back += 1_000) {
      const to = now - back;
      const until = readAheadTo(to, now);
      if (back <= REFRESH_MS) {
        // Reaches (almost) now: covers the clock until two refreshes from now.
        expect(until).toBeGreaterThanOrEqual(now + 2 * REFRESH_MS);
        expect(until).toBeGreaterThanOrEqual(to);
        // An end at or before now, sliding with the clock for two refreshes, stays inside.
        if (back >= 0) for (let slid = 0; slid <= 2 * REFRESH_MS; slid += 5_000) expect(to + slid <= until).toBe(true);
      } else {
        expect(until).toBe(to); // the past is read as asked
      }
    }
  });

  it("reads again only what may have grown: a span that ended a refresh before it was read is history", () => {
    const at = 1_800_000_000_000;
    for (let back = -120_000; back <= 600_000; back += 1_000) {
      expect(mayGrow(at - back, at)).toBe(back < REFRESH_MS);
    }
  });

  it("reads an instant's facts again once a refresh while live, every slack of playhead in the past (generated)", () => {
    const slack = 2_000;
    for (const back of [-5_000, 0, 3_000, 60_000, 3_600_000, 86_400_000]) {
      for (const speed of [0, 1, 60]) {
        const now0 = 1_800_000_000_000;
        let read: SpanRead = { t: -Infinity, until: -Infinity, at: 0 };
        let reads = 0;
        for (let wall = 0; wall <= 120_000; wall += 200) {
          const now = now0 + wall;
          // Live: the playhead is the clock; else `back` behind it at `speed`.
          const t = back === 0 ? now : now0 - back + wall * speed;
          if (!stillAnswers(read, t, now, slack)) {
            read = { t, until: readAheadTo(t + 1, now), at: now };
            reads++;
          }
          // Whatever answers is near the instant, or a read ahead past it not yet stale.
          expect(Math.abs(t - read.t) <= slack || (t < read.until && now - read.at <= REFRESH_MS)).toBe(true);
        }
        if (back === 0) expect(reads).toBeLessThanOrEqual(120_000 / REFRESH_MS + 1); // live: once a refresh
        if (back >= 60_000 && speed === 1) expect(reads).toBeGreaterThanOrEqual(120_000 / slack / 2); // the past: by the playhead
      }
    }
  });
});
