import { describe, expect, it } from "vitest";
import { agoText, formatUrlState, fromInputValue, parseUrlState, toInputValue } from "../src/lib/urlstate";

describe("url state", () => {
  it("round-trips time, speed, direction, play and view", () => {
    const s = { live: false, t: Date.UTC(2026, 10, 21, 10, 0, 5), speed: 3600 as const, dir: -1 as const,
      playing: true, view: { zoom: -1.5, lat: -100.5, lng: 200 }, follow: "r-1" };
    expect(parseUrlState(formatUrlState(s))).toEqual(s);
  });

  it("opens live when no time is given, and reads epoch ms or zone-less ISO as UTC", () => {
    expect(parseUrlState("").live).toBe(true);
    expect(parseUrlState("?t=1000").t).toBe(1000);
    expect(parseUrlState("?t=2026-11-21T10:00:00").t).toBe(Date.UTC(2026, 10, 21, 10));
    expect(parseUrlState("?speed=7").speed).toBe(1);
  });

  it("edits date-times to the second in UTC", () => {
    const t = Date.UTC(2026, 10, 21, 10, 0, 5);
    expect(fromInputValue(toInputValue(t))).toBe(t);
  });

  it("says how far from now", () => {
    expect(agoText(0, 3_723_000)).toBe("1 h 2 min ago");
    expect(agoText(1000, 1000)).toBe("now");
  });
});
