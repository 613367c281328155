import { describe, expect, it } from "vitest";
import { agoChangesIn, agoText, clampToRetention, formatUrlState, fromInputValue, parseUrlState, toInputValue } from "../src/lib/urlstate";

describe("url state", () => {
  it("round-trips time, speed, direction, play and view", () => {
    const s = { live: false, t: Date.UTC(2026, 10, 21, 10, 0, 5), speed: 3600 as const, dir: -1 as const,
      playing: true, view: { zoom: -1.5, lat: -100.5, lng: 200 }, follow: "r-1",
      layers: null, selected: null, panels: [], area: null, changeRobot: null, span: null, plot: [], incidentKinds: [], incidentRobot: null, incident: null, heatmap: null };
    expect(parseUrlState(formatUrlState(s))).toEqual({ ...s, tProblem: null });
  });

  it("round-trips layers, the selected robot, open panels and the change feed's filter", () => {
    const s = { live: false, t: Date.UTC(2026, 10, 21, 10), speed: 60 as const, dir: 1 as const, playing: false,
      view: null, follow: "sim-001",
      layers: { names: false, battery: true, paths: true, borders: true, info: true, infoMode: "writer" as const, conflicts: false, annotations: true },
      selected: "sim-001", panels: ["changes", "fleet", "annotations"], area: [1, 2, 3, 4] as [number, number, number, number], changeRobot: "sim-002",
      span: null, plot: [], incidentKinds: [], incidentRobot: null, incident: null, heatmap: null };
    const url = formatUrlState(s);
    expect(url).toContain("layers=battery%2Cpaths%2Cborders%2Cinfo-writer%2Cannotations");
    expect(parseUrlState(url)).toEqual({ ...s, tProblem: null });
    // No layer on is not the defaults: an empty list stays empty.
    expect(parseUrlState("?layers=").layers).toEqual({ names: false, battery: false, paths: false, borders: false, info: false, infoMode: "age", conflicts: false, annotations: false });
    expect(parseUrlState("?area=3,1,0,0&panels=changes,bogus").area).toBeNull();
    expect(parseUrlState("?panels=changes,bogus").panels).toEqual(["changes"]);
  });

  it("round-trips the timeline's span, the plots panel and the plotted robots", () => {
    const span: [number, number] = [Date.UTC(2026, 10, 21, 9, 30), Date.UTC(2026, 10, 21, 10, 15, 30)];
    const s = { live: false, t: Date.UTC(2026, 10, 21, 10), speed: 1 as const, dir: 1 as const, playing: false,
      view: null, follow: null, layers: null, selected: "sim-001", panels: ["fleet", "plots"], area: null,
      changeRobot: null, span, plot: ["sim-002", "sim-003"], incidentKinds: [], incidentRobot: null, incident: null, heatmap: null };
    const url = formatUrlState(s);
    expect(url).toContain("span=2026-11-21T09%3A30%3A00.000Z%2C2026-11-21T10%3A15%3A30.000Z");
    expect(parseUrlState(url)).toEqual({ ...s, tProblem: null });
    expect(parseUrlState(`?span=${span[0]},${span[1]}`).span).toEqual(span);
    // Backwards, under a second, or not times: the default span.
    expect(parseUrlState(`?span=${span[1]},${span[0]}`).span).toBeNull();
    expect(parseUrlState("?span=1000,1500").span).toBeNull();
    expect(parseUrlState("?span=soon,later").span).toBeNull();
  });

  it("live links carry no replay speed or direction", () => {
    const url = formatUrlState({ live: true, t: 5, speed: 3600, dir: -1, playing: true, view: null, follow: null,
      layers: null, selected: null, panels: [], area: null, changeRobot: null, span: null, plot: [], incidentKinds: [], incidentRobot: null, incident: null, heatmap: null });
    expect(url).toBe("?live=1");
  });

  it("says what is wrong with a time it cannot read, and opens live", () => {
    const s = parseUrlState("?t=yesterday-ish");
    expect(s.t).toBeNull();
    expect(s.live).toBe(true);
    expect(s.tProblem).toMatch(/t=yesterday-ish is not a time/);
  });

  it("brings a time outside the retention to the nearest kept instant and says so", () => {
    const now = Date.UTC(2026, 10, 21, 12);
    const week = 7 * 86_400_000;
    expect(clampToRetention(now - 3_600_000, now, week)).toEqual({ t: now - 3_600_000, problem: null });
    const old = clampToRetention(now - 30 * 86_400_000, now, week);
    expect(old.t).toBe(now - week + 60_000);
    expect(old.problem).toMatch(/older than the 7 days the history keeps/);
    expect(clampToRetention(now + 86_400_000, now, week)).toEqual({ t: now, problem: expect.stringMatching(/in the future/) });
  });

  it("opens live when no time is given, and reads epoch ms or zone-less ISO as UTC", () => {
    expect(parseUrlState("").live).toBe(true);
    expect(parseUrlState("?t=1000").t).toBe(1000);
    expect(parseUrlState("?t=2026-11-21T10:00:00").t).toBe(Date.UTC(2026, 10, 21, 10));
    expect(parseUrlState("?speed=7").speed).toBe(1);
  });

  it("edits date-times to the second in 24-hour UTC, and refuses what is not one", () => {
    const t = Date.UTC(2026, 10, 21, 22, 0, 5);
    expect(toInputValue(t)).toBe("2026-11-21 22:00:05");
    expect(fromInputValue(toInputValue(t))).toBe(t);
    expect(fromInputValue("2026-11-21T22:00")).toBe(Date.UTC(2026, 10, 21, 22));
    expect(fromInputValue("21/11/2026 10:00 PM")).toBeNull();
    // The address's own format, as copied from a link.
    expect(fromInputValue("2026-11-24T14:00:00Z")).toBe(Date.UTC(2026, 10, 24, 14));
    expect(fromInputValue("2026-11-24T14:00:00.250Z")).toBe(Date.UTC(2026, 10, 24, 14, 0, 0, 250));
    expect(fromInputValue("2026-11-24T14:00:00+02:00")).toBeNull();
    expect(fromInputValue("2026-13-45 99:00:00")).toBeNull();
  });

  it("says how far from now", () => {
    expect(agoText(0, 3_723_000)).toBe("1 h 2 min ago");
    expect(agoText(1000, 1000)).toBe("now");
  });

  it("knows when its text next changes: not before, and right then", () => {
    const at = Date.UTC(2026, 10, 21, 10, 0, 0, 123);
    // Elapsed times from a little in the future to ten days, at every sub-second offset.
    const elapsed = [-2500, -1, 0];
    for (let k = 1; k <= 2000; k++) elapsed.push(Math.floor(k ** 3 * 0.108) + ((k * 337) % 1000));
    for (const e of elapsed) {
      const now = at + e;
      const due = agoChangesIn(at, now);
      const text = agoText(at, now);
      expect(due, `${e}`).toBeGreaterThanOrEqual(1);
      expect(agoText(at, now + due - 1), `${e}`).toBe(text);
      expect(agoText(at, now + Math.floor(due / 2)), `${e}`).toBe(text);
      expect(agoText(at, now + due), `${e}`).not.toBe(text);
    }
    // Its resolution: a second under an hour, a minute under a day, an hour beyond.
    expect(agoChangesIn(at, at + 600_000)).toBeLessThanOrEqual(1000);
    expect(agoChangesIn(at, at + 7_200_000)).toBeGreaterThan(1000);
    expect(agoChangesIn(at, at + 2 * 86_400_000)).toBeGreaterThan(60_000);
  });
});
