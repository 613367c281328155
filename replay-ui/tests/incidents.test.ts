import { describe, expect, it } from "vitest";
import { chunkAt } from "../src/lib/geo";
import {
  applyAnnouncement, incidentSeek, incidentsUrl, inArea, KINDS, laneCounts, laneText, LEAD_MS, matchesQuery, meets,
  measureText, neighbourIncident, shownIncidents, sortByStart, trailWindow, type Incident, type IncidentKind,
} from "../src/lib/incidents";
import { keyAction, type ReplayKeyActions } from "../src/composables/useReplayKeys";
import { formatUrlState, parseUrlState } from "../src/lib/urlstate";
import type { MapMeta } from "../src/lib/types";

function random(seed: number) {
  return () => {
    seed = (seed * 1103515245 + 12345) % 2147483648;
    return seed / 2147483648;
  };
}

const T0 = Date.UTC(2026, 10, 30, 6);
const ROBOTS = ["r1", "r2", "r3", "sim-004"];
const META: MapMeta = { width: 400, height: 300, CHUNK_WIDTH: 50, CHUNK_HEIGHT: 50, CHUNK_ROWS: 6, CHUNK_COLS: 8,
  resolution: 0.05, origin: [-5, -5, 0] };

function incidentsOf(rnd: () => number, n: number): Incident[] {
  return Array.from({ length: n }, (_, k) => {
    const kind = KINDS[Math.floor(rnd() * KINDS.length)];
    const a = ROBOTS[Math.floor(rnd() * ROBOTS.length)];
    const b = ROBOTS.filter((r) => r !== a)[Math.floor(rnd() * (ROBOTS.length - 1))];
    // Starts on whole seconds, some shared: incidents of one instant happen.
    const start = T0 + Math.floor(rnd() * 3600) * 1000;
    return {
      id: `i${k}`, kind, robots: kind === "near_miss" ? [a, b].sort() : [a], start_ms: start,
      end_ms: start + Math.floor(rnd() * 600_000), ongoing: rnd() < 0.1, x: -5 + rnd() * 20, y: -5 + rnd() * 15,
      severity: rnd() < 0.2 ? "critical" : "warning", measure: rnd() * 60, evidence: [],
    };
  });
}

describe("incidents", () => {
  it("asks the server for the span with the kinds and the robot", () => {
    const url = new URL(incidentsUrl("http://h", 1000.5, 2000.2, { kinds: ["stuck", "offline"], robot: "r 1" }, 500));
    expect(url.pathname).toBe("/api/v1/incidents");
    expect(url.searchParams.get("from")).toBe("1000");
    expect(url.searchParams.get("to")).toBe("2001");
    expect(url.searchParams.getAll("kind")).toEqual(["stuck", "offline"]);
    expect(url.searchParams.get("robot")).toBe("r 1");
    expect(url.searchParams.get("limit")).toBe("500");
    expect(new URL(incidentsUrl("", 0, 1, { kinds: [], robot: null }, 5), "http://h").searchParams.has("kind")).toBe(false);
  });

  it("lists those meeting the span in the area drawn, and filters as the server does", () => {
    const rnd = random(3);
    for (let round = 0; round < 200; round++) {
      const items = incidentsOf(rnd, 40);
      const from = T0 + Math.floor(rnd() * 3_000_000);
      const to = from + 1 + Math.floor(rnd() * 2_000_000);
      const r0 = Math.floor(rnd() * 6), c0 = Math.floor(rnd() * 8);
      const box = rnd() < 0.2 ? null : { rowMin: r0, rowMax: r0 + Math.floor(rnd() * 3), colMin: c0, colMax: c0 + Math.floor(rnd() * 3) };
      const shown = shownIncidents(items, [from, to], box, META);
      for (const i of items) {
        const c = chunkAt(META, i.x, i.y);
        const inBox = !box || (!!c && c.row >= box.rowMin && c.row <= box.rowMax && c.column >= box.colMin && c.column <= box.colMax);
        expect(shown.includes(i)).toBe(i.start_ms < to && i.end_ms >= from && inBox);
      }
      const kinds = KINDS.filter(() => rnd() < 0.5);
      const robot = rnd() < 0.5 ? null : ROBOTS[Math.floor(rnd() * ROBOTS.length)];
      for (const i of items) {
        expect(matchesQuery(i, { kinds, robot })).toBe((!kinds.length || kinds.includes(i.kind)) && (!robot || i.robots.includes(robot)));
      }
    }
    // No map yet: the area cannot be told, nothing is hidden.
    expect(inArea({ x: 1e6, y: 1e6 }, { rowMin: 0, rowMax: 0, colMin: 0, colMax: 0 }, null)).toBe(true);
  });

  it("counts each incident once, per kind, in the lane bucket of its start", () => {
    const rnd = random(5);
    for (let round = 0; round < 200; round++) {
      const items = incidentsOf(rnd, 1 + Math.floor(rnd() * 60));
      const from = T0 + Math.floor(rnd() * 1_000_000);
      const to = from + 1000 + Math.floor(rnd() * 4_000_000);
      const n = 1 + Math.floor(rnd() * 300);
      const lane = laneCounts(items, from, to, n);
      const within = items.filter((i) => meets(i, from, to));
      expect(lane.reduce((s, b) => s + b.total, 0)).toBe(within.length);
      for (const k of KINDS) {
        expect(lane.reduce((s, b) => s + (b.counts[k] ?? 0), 0)).toBe(within.filter((i) => i.kind === k).length);
      }
      const width = (to - from) / n;
      for (const i of within) {
        const t = Math.max(i.start_ms, from);
        const b = lane.find((x) => x.start_ms <= t && t < x.end_ms + 1e-6);
        expect(b, `${i.id} in no bucket`).toBeTruthy();
      }
      for (const b of lane) {
        expect(b.end_ms - b.start_ms).toBeCloseTo(width, 3);
        expect(b.total).toBe(Object.values(b.counts).reduce((s, v) => s + (v ?? 0), 0));
      }
      expect(lane.map((b) => b.start_ms)).toEqual([...lane.map((b) => b.start_ms)].sort((a, b) => a - b));
    }
    expect(laneText({ start_ms: 0, end_ms: 1, counts: { near_miss: 2, stuck: 1 }, total: 3 })).toBe("2 near misses · 1 stuck");
  });

  it("steps to the previous and next incident, visiting each one of a shared instant", () => {
    const rnd = random(7);
    for (let round = 0; round < 200; round++) {
      const sorted = sortByStart(incidentsOf(rnd, 1 + Math.floor(rnd() * 30)));
      // Walking forwards from before the first with `]` visits every incident in order, then stops.
      let playhead = sorted[0].start_ms - LEAD_MS - 1 - Math.floor(rnd() * 1000);
      let picked: string | null = null;
      const seen: string[] = [];
      for (;;) {
        const next = neighbourIncident(sorted, picked, playhead, 1);
        if (!next) break;
        seen.push(next.id);
        picked = next.id;
        playhead = incidentSeek(next);
      }
      expect(seen).toEqual(sorted.map((i) => i.id));
      // And backwards with `[` from there.
      const back: string[] = [picked!];
      for (;;) {
        const prev = neighbourIncident(sorted, picked, playhead, -1);
        if (!prev) break;
        back.push(prev.id);
        picked = prev.id;
        playhead = incidentSeek(prev);
      }
      expect(back).toEqual(sorted.map((i) => i.id).reverse());
      // From a playhead moved elsewhere: the nearest pick target on that side.
      const t = T0 + Math.floor(rnd() * 3_600_000);
      const after = neighbourIncident(sorted, picked, t, 1);
      expect(after).toBe(sorted.find((i) => incidentSeek(i) > t) ?? null);
      const before = neighbourIncident(sorted, null, t, -1);
      expect(before).toBe([...sorted].reverse().find((i) => incidentSeek(i) < t) ?? null);
    }
  });

  it("merges a live announcement: a new one joins in order, a later finding replaces, a retraction drops", () => {
    const rnd = random(9);
    const read = { from: T0, to: T0 + 3_600_000 };
    for (let round = 0; round < 100; round++) {
      const all = incidentsOf(rnd, 20);
      const q = { kinds: KINDS.filter(() => rnd() < 0.5), robot: rnd() < 0.5 ? null : ROBOTS[0] };
      let list: Incident[] = [];
      const expected = new Map<string, Incident>();
      for (let step = 0; step < 40; step++) {
        const base = all[Math.floor(rnd() * all.length)];
        const retracted = rnd() < 0.25;
        const incident = { ...base, end_ms: base.end_ms + Math.floor(rnd() * 5000) };
        list = applyAnnouncement(list, { retracted, incident }, read, q);
        if (retracted || !matchesQuery(incident, q) || !meets(incident, read.from, read.to)) expected.delete(incident.id);
        else expected.set(incident.id, incident);
        expect(list).toEqual(sortByStart([...expected.values()]));
      }
    }
  });

  it("keeps the panel's filters and its pick in the address", () => {
    const rnd = random(13);
    for (let round = 0; round < 100; round++) {
      const s = { live: false, t: T0, speed: 1 as const, dir: 1 as const, playing: false, view: null, follow: null, layers: null,
        selected: null, panels: rnd() < 0.5 ? ["incidents"] : ["changes", "incidents"], area: [1, 2, 0, 3] as [number, number, number, number],
        changeRobot: null, span: null, plot: [],
        incidentKinds: KINDS.filter(() => rnd() < 0.5) as string[],
        incidentRobot: rnd() < 0.5 ? null : `robot ${Math.floor(rnd() * 9)}/ü`,
        incident: rnd() < 0.3 ? null : Math.floor(rnd() * 2 ** 40).toString(16), heatmap: null };
      expect(parseUrlState(formatUrlState(s))).toEqual({ ...s, tProblem: null });
    }
    expect(formatUrlState({ ...parseUrlState("?t=5"), incidentKinds: ["stuck", "offline"], incidentRobot: "r1", incident: "abc" }))
      .toContain("ikind=stuck%2Coffline&irobot=r1&inc=abc");
  });

  it("says each kind's figure in words and seeks a few seconds before the start", () => {
    const i = (kind: IncidentKind, measure: number, ongoing = false) => ({ kind, measure, ongoing });
    expect(measureText(i("near_miss", 0.4234))).toBe("0.42 m apart");
    expect(measureText(i("stuck", 45))).toBe("stuck 45 s");
    expect(measureText(i("offline", 125, true))).toBe("silent 2 min 5 s so far");
    expect(measureText(i("battery_low", 12.4))).toBe("lowest 12 %");
    expect(measureText(i("zone_violation", 8, true))).toBe("inside 8 s so far");
    expect(measureText(i("conflict", 1))).toBe("1 chunk write");
    expect(measureText(i("conflict", 3))).toBe("3 chunk writes");
    expect(measureText(i("vda_error", 40))).toBe("error 40 s");
    expect(measureText(i("command_failed", 10))).toBe("waited 10 s");
    expect(incidentSeek({ start_ms: T0 })).toBe(T0 - LEAD_MS);
    expect(LEAD_MS).toBeGreaterThanOrEqual(2000);
    const [a, b] = trailWindow({ start_ms: T0, end_ms: T0 + 3 * 3_600_000 });
    expect(a).toBeLessThan(incidentSeek({ start_ms: T0 }));
    expect(b - T0).toBeLessThanOrEqual(11 * 60_000);
  });

  it("[ and ] step through incidents, and leave the other keys as they were", () => {
    const calls: string[] = [];
    const a: ReplayKeyActions = {
      togglePlay: () => calls.push("play"), step: (d) => calls.push(`step${d}`), stepChange: (d) => calls.push(`change${d}`),
      stepIncident: (d) => calls.push(`incident${d}`), speedBy: (d) => calls.push(`speed${d}`), goLive: () => calls.push("live"),
      unselect: () => calls.push("esc"),
    };
    for (const [key, shiftKey] of [["[", false], ["]", false], ["ArrowLeft", true], ["ArrowRight", false], [" ", false], ["Escape", false]] as const) {
      keyAction({ key, shiftKey }, a)?.();
    }
    expect(calls).toEqual(["incident-1", "incident1", "change-1", "step1", "play", "esc"]);
  });
});
