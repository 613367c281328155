/**
 * Operators' annotations as the replay draws and edits them: the API's shapes, and the
 * pure geometry and time bookkeeping behind them (hatching a keep-out zone, closing a
 * drawn polygon, when the annotations at the playhead must be read again, violations
 * grouped into episodes). Leaflet stays out of this module (lib/annotationlayer.ts).
 */

export type Point = [number, number]; // map metres

export const POI_KINDS = ["station", "charger", "door", "note"] as const;
export const ZONE_KINDS = ["keep_out", "speed_limit", "note"] as const;
export type PoiKind = (typeof POI_KINDS)[number];
export type ZoneKind = (typeof ZONE_KINDS)[number];

export interface PoiDoc {
  shape: "poi";
  name: string;
  kind: PoiKind;
  x: number;
  y: number;
  heading?: number | null;
  note?: string;
}

export interface ZoneDoc {
  shape: "zone";
  name: string;
  kind: ZoneKind;
  polygon: Point[];
  holes?: Point[][];
  speed_limit?: number | null;
  speed_unit?: "percent" | "m/s" | null;
  note?: string;
}

export type AnnotationDoc = PoiDoc | ZoneDoc;

/** One annotation standing at an instant (GET /api/v1/annotations). */
export interface Annotation {
  id: string;
  annotation: AnnotationDoc;
  created_ms: number;
  created_by: string;
  changed_ms: number;
  changed_by: string;
}

/** One create, change or removal (GET /api/v1/annotations/edits). */
export interface AnnotationEdit {
  ts_ms: number;
  event_id: string;
  id: string;
  change: "created" | "changed" | "removed";
  by: string;
  annotation: AnnotationDoc | null;
}

/** A stored pose inside a keep-out zone (GET /api/v1/zone-violations). */
export interface ZoneViolation {
  ts_ms: number;
  robotId: string;
  zoneId: string;
  x: number;
  y: number;
}

/** How a zone's speed limit reads: "0.5 m/s", "30 %". */
export function speedText(z: ZoneDoc): string {
  if (z.kind !== "speed_limit" || z.speed_limit == null) return "";
  return z.speed_unit === "percent" ? `${z.speed_limit} %` : `${z.speed_limit} m/s`;
}

/** How strongly a speed zone is tinted: the slower it makes robots, the stronger. */
export function speedTint(z: ZoneDoc): number {
  const v = z.speed_limit ?? 0;
  const frac = z.speed_unit === "percent" ? v / 100 : v / 2; // 2 m/s: a fast AGV, no tint
  return 0.12 + 0.38 * (1 - Math.min(1, Math.max(0, frac)));
}

/** A one-line description of an annotation, for lists and tooltips. */
export function describe(a: AnnotationDoc): string {
  if (a.shape === "poi") return `${a.name} (${a.kind})`;
  const kind = a.kind === "keep_out" ? "keep-out" : a.kind === "speed_limit" ? `speed ≤ ${speedText(a)}` : "note";
  return `${a.name} (${kind} zone)`;
}

/**
 * Whether the annotations read at `loadedAt` still hold at `t`: no edit of `edits` lies
 * between them. Edits count at their instant (the API's annotations at T include the edits
 * stamped T), so an edit at e changes what stands for t >= e: it is crossed when it lies in
 * (min, max] of the two instants.
 */
export function crossesEdit(edits: readonly { ts_ms: number }[], loadedAt: number, t: number): boolean {
  const lo = Math.min(loadedAt, t);
  const hi = Math.max(loadedAt, t);
  return edits.some((e) => e.ts_ms > lo && e.ts_ms <= hi);
}

/**
 * The vertices a user clicked, as a polygon: a double-click's two clicks add the closing
 * point twice (or more), and a user may click the first vertex again to close; vertices
 * within `tolerance` metres of the previous one (or of the first, at the end) are dropped.
 * Null when fewer than three distinct vertices remain.
 */
export function closeRing(clicked: readonly Point[], tolerance: number): Point[] | null {
  const out: Point[] = [];
  for (const p of clicked) {
    const last = out[out.length - 1];
    if (!last || Math.hypot(p[0] - last[0], p[1] - last[1]) > tolerance) out.push([p[0], p[1]]);
  }
  while (out.length > 1 && Math.hypot(out[0][0] - out[out.length - 1][0], out[0][1] - out[out.length - 1][1]) <= tolerance) out.pop();
  if (out.length < 3) return null;
  return Math.abs(signedArea(out)) > tolerance * tolerance ? out : null;
}

/** The shoelace area (positive counter-clockwise) of a ring, in m². */
export function signedArea(ring: readonly Point[]): number {
  let a = 0;
  for (let i = 0; i < ring.length; i++) {
    const [x1, y1] = ring[i];
    const [x2, y2] = ring[(i + 1) % ring.length];
    a += x1 * y2 - x2 * y1;
  }
  return a / 2;
}

/** Whether a point lies inside a ring (even-odd rule; a point on an edge may go either way). */
export function insideRing(ring: readonly Point[], x: number, y: number): boolean {
  let inside = false;
  for (let i = 0, j = ring.length - 1; i < ring.length; j = i++) {
    const [xi, yi] = ring[i];
    const [xj, yj] = ring[j];
    if (yi > y !== yj > y && x < ((xj - xi) * (y - yi)) / (yj - yi) + xi) inside = !inside;
  }
  return inside;
}

/** Whether a point lies in a zone: inside its polygon and in none of its holes. */
export function insideZone(z: ZoneDoc, x: number, y: number): boolean {
  return insideRing(z.polygon, x, y) && !(z.holes ?? []).some((h) => insideRing(h, x, y));
}

/**
 * The hatching of a zone: segments of the 45° lines x - y = c, `spacing` metres apart
 * (measured along x), clipped to the zone (holes left out, even-odd rule). Renderer-free, so
 * the canvas draws it as plain polylines.
 */
export function hatchSegments(z: ZoneDoc, spacing: number): [Point, Point][] {
  const rings = [z.polygon, ...(z.holes ?? [])].filter((r) => r.length >= 3);
  if (!rings.length || !(spacing > 0)) return [];
  let lo = Infinity;
  let hi = -Infinity;
  for (const r of rings) for (const [x, y] of r) {
    lo = Math.min(lo, x - y);
    hi = Math.max(hi, x - y);
  }
  const out: [Point, Point][] = [];
  // Lines on multiples of `spacing`: neighbouring zones' hatchings line up.
  for (let c = Math.ceil(lo / spacing) * spacing; c <= hi; c += spacing) {
    // Parametrise the line as (c + s, s): an edge crossing it gives one s.
    const ss: number[] = [];
    for (const r of rings) {
      for (let i = 0; i < r.length; i++) {
        const [x1, y1] = r[i];
        const [x2, y2] = r[(i + 1) % r.length];
        const d1 = x1 - y1 - c;
        const d2 = x2 - y2 - c;
        if (d1 > 0 === d2 > 0) continue; // half-open: a vertex on the line counts once
        const f = d1 / (d1 - d2);
        ss.push(y1 + f * (y2 - y1));
      }
    }
    ss.sort((a, b) => a - b);
    for (let k = 0; k + 1 < ss.length; k += 2) {
      if (ss[k + 1] - ss[k] > 1e-9) out.push([[c + ss[k], ss[k]], [c + ss[k + 1], ss[k + 1]]]);
    }
  }
  return out;
}

/** The hatch spacing that draws a zone with about `lines` lines across its bounding box (≥ 0.2 m). */
export function hatchSpacing(ring: readonly Point[], lines = 24): number {
  const xs = ring.map((p) => p[0]);
  const ys = ring.map((p) => p[1]);
  const span = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys));
  return Math.max(0.2, (2 * span) / lines);
}

/** The centre of a ring's vertices (where a zone's label goes). */
export function centroid(ring: readonly Point[]): Point {
  const n = ring.length || 1;
  return [ring.reduce((s, p) => s + p[0], 0) / n, ring.reduce((s, p) => s + p[1], 0) / n];
}

/** A ring moved by (dx, dy) metres: a zone dragged. */
export function translate(ring: readonly Point[], dx: number, dy: number): Point[] {
  return ring.map(([x, y]) => [x + dx, y + dy]);
}

/** A zone moved by (dx, dy) metres, holes and all (a zone dragged). */
export function movedZone(z: ZoneDoc, dx: number, dy: number): ZoneDoc {
  return { ...z, polygon: translate(z.polygon, dx, dy), holes: (z.holes ?? []).map((h) => translate(h, dx, dy)) };
}

/** The annotations' documents as the API takes them back (PUT): null fields left out. */
export function bodyOf(a: AnnotationDoc): Record<string, unknown> {
  return Object.fromEntries(Object.entries(a).filter(([, v]) => v !== null && v !== undefined));
}

/**
 * This page's own edits at or before `t` that the annotations read at `t` do not show
 * yet: a read made before the store held them (they reach it a second or so after the
 * API took them). A creation or change shows as the annotation changed at its instant or
 * later, a removal as the annotation gone.
 */
export function unreflectedEdits(mine: readonly AnnotationEdit[], list: readonly Annotation[], t: number): AnnotationEdit[] {
  const byId = new Map(list.map((a) => [a.id, a]));
  return mine.filter((e) => {
    if (e.ts_ms > t) return false;
    const a = byId.get(e.id);
    return e.change === "removed" ? a !== undefined : a === undefined || a.changed_ms < e.ts_ms;
  });
}

/** The store's record of an edit this page made (a removal's instant is known only roughly: the server's clock). */
export function sameEdit(stored: AnnotationEdit, mine: AnnotationEdit): boolean {
  return stored.id === mine.id && stored.change === mine.change
    && (stored.ts_ms === mine.ts_ms || (mine.change === "removed" && Math.abs(stored.ts_ms - mine.ts_ms) < 5_000));
}

/** A robot's stay inside one keep-out zone: its stored poses there, no more than `gapMs` apart. */
export interface ViolationEpisode {
  robotId: string;
  zoneId: string;
  from_ms: number;
  to_ms: number;
  poses: number;
  x: number; // the first pose inside
  y: number;
}

/** Violations (any order) as episodes, the latest first. */
export function violationEpisodes(vs: readonly ZoneViolation[], gapMs = 10_000): ViolationEpisode[] {
  const sorted = [...vs].sort((a, b) => a.ts_ms - b.ts_ms);
  const open = new Map<string, ViolationEpisode>();
  const out: ViolationEpisode[] = [];
  for (const v of sorted) {
    const key = `${v.robotId}\u0000${v.zoneId}`;
    const e = open.get(key);
    if (e && v.ts_ms - e.to_ms <= gapMs) {
      e.to_ms = v.ts_ms;
      e.poses++;
      continue;
    }
    const fresh = { robotId: v.robotId, zoneId: v.zoneId, from_ms: v.ts_ms, to_ms: v.ts_ms, poses: 1, x: v.x, y: v.y };
    open.set(key, fresh);
    out.push(fresh);
  }
  return out.sort((a, b) => b.from_ms - a.from_ms || a.robotId.localeCompare(b.robotId));
}

/** The violations the map shows at `t`: each robot's latest one within `windowMs` before it. */
export function violationsAt(vs: readonly ZoneViolation[], t: number, windowMs: number): ZoneViolation[] {
  const latest = new Map<string, ZoneViolation>();
  for (const v of vs) {
    if (v.ts_ms > t || v.ts_ms < t - windowMs) continue;
    const seen = latest.get(v.robotId);
    if (!seen || v.ts_ms > seen.ts_ms) latest.set(v.robotId, v);
  }
  return [...latest.values()].sort((a, b) => a.robotId.localeCompare(b.robotId));
}

/** A tick on the timeline: an annotation's edit or a violation episode's start. */
export interface TimelineMark {
  key: string;
  ts_ms: number;
  kind: "annotation-edit" | "zone-violation" | "command";
  title: string;
}

/** The timeline's marks for the edits and the violation episodes of its span. */
export function timelineMarks(edits: readonly AnnotationEdit[], episodes: readonly ViolationEpisode[]): TimelineMark[] {
  const names = new Map<string, string>();
  for (const e of edits) if (e.annotation) names.set(e.id, e.annotation.name);
  return [
    ...edits.map((e): TimelineMark => ({
      key: `e:${e.event_id}`, ts_ms: e.ts_ms, kind: "annotation-edit",
      title: `${names.get(e.id) ?? e.id} ${e.change} by ${e.by}`,
    })),
    ...episodes.map((v): TimelineMark => ({
      key: `v:${v.robotId}:${v.zoneId}:${v.from_ms}`, ts_ms: v.from_ms, kind: "zone-violation",
      title: `${v.robotId} inside keep-out zone ${names.get(v.zoneId) ?? v.zoneId} (${v.poses} pose${v.poses === 1 ? "" : "s"})`,
    })),
  ];
}
