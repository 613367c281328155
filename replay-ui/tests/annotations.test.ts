import { describe, expect, it } from "vitest";
import {
  bodyOf, closeRing, movedZone, sameEdit, speedTint, timelineMarks, type Annotation, type AnnotationEdit, crossesEdit, describe as describeAnnotation, hatchSegments, insideRing, insideZone,
  signedArea, translate, unreflectedEdits, violationEpisodes, violationsAt, type Point, type ZoneDoc, type ZoneViolation,
} from "../src/lib/annotations";

const square: Point[] = [[0, 0], [4, 0], [4, 4], [0, 4]];
const keepOut: ZoneDoc = { shape: "zone", name: "aisle", kind: "keep_out", polygon: square };

describe("crossesEdit", () => {
  const edits = [{ ts_ms: 100 }, { ts_ms: 200 }];
  it("is crossed when an edit lies after the read instant and at or before the new one", () => {
    expect(crossesEdit(edits, 50, 99)).toBe(false);
    expect(crossesEdit(edits, 50, 100)).toBe(true); // the edit stamped T stands at T
    expect(crossesEdit(edits, 100, 199)).toBe(false);
    expect(crossesEdit(edits, 150, 250)).toBe(true);
  });
  it("works backwards too", () => {
    expect(crossesEdit(edits, 150, 120)).toBe(false);
    expect(crossesEdit(edits, 150, 99)).toBe(true);
    expect(crossesEdit(edits, 100, 99)).toBe(true); // at 100 it stood, at 99 not yet
  });
});

describe("closeRing", () => {
  it("drops the double-click's repeated vertex and a click back on the first", () => {
    expect(closeRing([[0, 0], [4, 0], [4, 4], [4, 4.01], [4, 4]], 0.1)).toEqual([[0, 0], [4, 0], [4, 4]]);
    expect(closeRing([[0, 0], [4, 0], [4, 4], [0.02, 0]], 0.1)).toEqual([[0, 0], [4, 0], [4, 4]]);
  });
  it("refuses fewer than three distinct vertices and a ring without area", () => {
    expect(closeRing([[0, 0], [4, 0], [4, 0.05]], 0.1)).toBeNull();
    expect(closeRing([[0, 0], [1, 1], [2, 2]], 0.1)).toBeNull();
    expect(closeRing([], 0.1)).toBeNull();
  });
});

describe("geometry", () => {
  it("measures the signed area", () => {
    expect(signedArea(square)).toBe(16);
    expect(signedArea([...square].reverse())).toBe(-16);
  });
  it("finds points inside a zone but not in its holes", () => {
    const holed: ZoneDoc = { ...keepOut, holes: [[[1, 1], [3, 1], [3, 3], [1, 3]]] };
    expect(insideRing(square, 2, 2)).toBe(true);
    expect(insideRing(square, 5, 2)).toBe(false);
    expect(insideZone(holed, 0.5, 0.5)).toBe(true);
    expect(insideZone(holed, 2, 2)).toBe(false);
  });
  it("moves a ring", () => {
    expect(translate(square, 1, -2)[2]).toEqual([5, 2]);
  });
});

describe("hatchSegments", () => {
  it("covers the zone with 45° segments whose ends lie on its edges", () => {
    const segs = hatchSegments(keepOut, 1);
    // x - y runs from -4 to 4 over the square: lines at -4..4, the corners' lines are points.
    expect(segs.length).toBe(7);
    for (const [a, b] of segs) {
      expect(a[0] - a[1]).toBeCloseTo(b[0] - b[1], 9); // on one 45° line
      for (const p of [a, b]) {
        const onEdge = [p[0], p[1]].some((v) => Math.abs(v) < 1e-9 || Math.abs(v - 4) < 1e-9);
        expect(onEdge).toBe(true);
      }
    }
    // The diagonal x = y crosses the whole square.
    const diag = segs.find(([a]) => Math.abs(a[0] - a[1]) < 1e-9)!;
    expect(Math.hypot(diag[1][0] - diag[0][0], diag[1][1] - diag[0][1])).toBeCloseTo(Math.hypot(4, 4), 9);
  });
  it("leaves holes unhatched", () => {
    const holed: ZoneDoc = { ...keepOut, holes: [[[1, 1], [3, 1], [3, 3], [1, 3]]] };
    const segs = hatchSegments(holed, 1);
    for (const [a, b] of segs) {
      const mid: [number, number] = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2];
      expect(insideZone(holed, mid[0], mid[1])).toBe(true);
    }
    // The diagonal is cut in two by the hole.
    expect(segs.filter(([a]) => Math.abs(a[0] - a[1]) < 1e-9).length).toBe(2);
  });
  it("draws nothing for a degenerate zone or spacing", () => {
    expect(hatchSegments({ ...keepOut, polygon: [[0, 0], [1, 1]] }, 1)).toEqual([]);
    expect(hatchSegments(keepOut, 0)).toEqual([]);
  });
});

describe("violations", () => {
  const v = (ts_ms: number, robotId = "r1", zoneId = "z1"): ZoneViolation => ({ ts_ms, robotId, zoneId, x: ts_ms / 1000, y: 1 });
  it("groups a robot's poses in one zone into episodes split by gaps", () => {
    const eps = violationEpisodes([v(30_000), v(1_000), v(2_000), v(5_000, "r2"), v(3_000, "r1", "z2")]);
    expect(eps.map((e) => [e.robotId, e.zoneId, e.from_ms, e.to_ms, e.poses])).toEqual([
      ["r1", "z1", 30_000, 30_000, 1],
      ["r2", "z1", 5_000, 5_000, 1],
      ["r1", "z2", 3_000, 3_000, 1],
      ["r1", "z1", 1_000, 2_000, 2],
    ]);
    expect(eps[3].x).toBe(1); // where it first was inside
  });
  it("shows each robot's latest violation in the window before the playhead", () => {
    const vs = [v(1_000), v(4_000), v(9_000), v(3_000, "r2"), v(20_000, "r3")];
    expect(violationsAt(vs, 5_000, 3_000).map((x) => [x.robotId, x.ts_ms])).toEqual([["r1", 4_000], ["r2", 3_000]]);
  });
});

describe("documents", () => {
  it("describes zones and points", () => {
    expect(describeAnnotation(keepOut)).toBe("aisle (keep-out zone)");
    expect(describeAnnotation({ ...keepOut, kind: "speed_limit", speed_limit: 0.5, speed_unit: "m/s" })).toBe("aisle (speed ≤ 0.5 m/s zone)");
    expect(describeAnnotation({ shape: "poi", name: "dock 1", kind: "charger", x: 1, y: 2 })).toBe("dock 1 (charger)");
  });
  it("leaves null fields out of a body sent back", () => {
    expect(bodyOf({ shape: "poi", name: "a", kind: "door", x: 1, y: 2, heading: null })).toEqual({ shape: "poi", name: "a", kind: "door", x: 1, y: 2 });
  });
});

describe("edits", () => {
  const created: AnnotationEdit = { ts_ms: 1_000, event_id: "e1", id: "z1", change: "created", by: "operator:ab", annotation: keepOut };
  it("marks edits and violation episodes on the timeline, naming the zone", () => {
    const marks = timelineMarks([created], violationEpisodes([{ ts_ms: 2_000, robotId: "r1", zoneId: "z1", x: 0, y: 0 }]));
    expect(marks.map((m) => [m.kind, m.ts_ms, m.title])).toEqual([
      ["annotation-edit", 1_000, "aisle created by operator:ab"],
      ["zone-violation", 2_000, "r1 inside keep-out zone aisle (1 pose)"],
    ]);
  });
  it("knows the store's record of this page's own edit", () => {
    expect(sameEdit(created, { ...created, event_id: "local" })).toBe(true);
    expect(sameEdit({ ...created, ts_ms: 1_001 }, created)).toBe(false);
    const removed: AnnotationEdit = { ...created, change: "removed", annotation: null };
    expect(sameEdit({ ...removed, ts_ms: 3_000 }, removed)).toBe(true); // a removal's instant is the server's
    expect(sameEdit(removed, created)).toBe(false);
  });
  it("moves a zone with its holes, and tints slower zones more", () => {
    const z = movedZone({ ...keepOut, holes: [[[1, 1], [2, 1], [2, 2]]] }, 1, 2);
    expect(z.polygon[0]).toEqual([1, 2]);
    expect(z.holes![0][2]).toEqual([3, 4]);
    const slow = speedTint({ ...keepOut, kind: "speed_limit", speed_limit: 0.2, speed_unit: "m/s" });
    const fast = speedTint({ ...keepOut, kind: "speed_limit", speed_limit: 1.5, speed_unit: "m/s" });
    expect(slow).toBeGreaterThan(fast);
    expect(speedTint({ ...keepOut, kind: "speed_limit", speed_limit: 100, speed_unit: "percent" })).toBeCloseTo(0.12, 9);
  });
});

describe("unreflectedEdits", () => {
  const doc: ZoneDoc = keepOut;
  const stored = (id: string, changed: number): Annotation =>
    ({ id, annotation: doc, created_ms: 10, created_by: "o", changed_ms: changed, changed_by: "o" });
  const edit = (id: string, change: AnnotationEdit["change"], ts: number): AnnotationEdit =>
    ({ ts_ms: ts, event_id: `local:${ts}`, id, change, by: "you", annotation: change === "removed" ? null : doc });
  // Every kind of edit against a list that shows it, one read before the store had it, and an instant before the edit.
  const cases: [AnnotationEdit, Annotation[], Annotation[]][] = [
    [edit("z", "created", 100), [stored("z", 100)], []],
    [edit("z", "changed", 100), [stored("z", 100)], [stored("z", 60)]],
    [edit("z", "changed", 100), [stored("z", 150)], [stored("z", 99)]], // changed again later: shown
    [edit("z", "removed", 100), [], [stored("z", 60)]],
  ];
  it.each(cases)("finds an edit the read at or after it does not show (%o)", (e, shows, stale) => {
    expect(unreflectedEdits([e], shows, 100)).toEqual([]);
    expect(unreflectedEdits([e], shows, 5_000)).toEqual([]);
    expect(unreflectedEdits([e], stale, 100)).toEqual([e]);
    expect(unreflectedEdits([e], stale, 5_000)).toEqual([e]);
    expect(unreflectedEdits([e], stale, 99)).toEqual([]); // before the edit, the old state is right
    expect(unreflectedEdits([e], [...stale, stored("other", 100)], 100)).toEqual([e]);
  });
});
