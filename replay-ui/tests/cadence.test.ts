import { describe, expect, it } from "vitest";
import { mayGrow, readAheadTo, REFRESH_MS } from "../src/lib/cadence";

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
});
