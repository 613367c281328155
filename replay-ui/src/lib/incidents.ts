/**
 * The incidents (GET /api/v1/incidents, and the live stream's announcements) as the replay's
 * panel and timeline need them: the request, the panel's filters (kinds and robot asked of
 * the server, the area drawn on the map applied here: the API has no area), the live
 * announcements merged into what was read, the timeline lane's counts per kind, where a
 * pick seeks, and the previous/next incident from the playhead.
 *
 * Pure.
 */
import type { components } from "./api-schema";
import type { ChunkBox } from "./changefeed";
import { chunkAt } from "./geo";
import type { MapMeta } from "./types";

export type Incident = components["schemas"]["Incident"];
export type IncidentKind = Incident["kind"];

/** An incident announced on the live stream (mapservice/core/live_incidents.py). */
export interface IncidentAnnouncement {
  type: "incident";
  ts_ms: number;
  sent_ms?: number;
  retracted: boolean;
  incident: Incident;
}

/** Each kind's words (one, several) and colour (the panel's swatch, the lane, the marker on the map). */
export const KIND_STYLE: Record<IncidentKind, { label: string; many: string; colour: string }> = {
  near_miss: { label: "near miss", many: "near misses", colour: "#d62728" },
  stuck: { label: "stuck", many: "stuck", colour: "#ff7f0e" },
  offline: { label: "offline", many: "offline", colour: "#7f7f7f" },
  battery_low: { label: "battery low", many: "battery low", colour: "#b8a000" },
  zone_violation: { label: "zone violation", many: "zone violations", colour: "#9467bd" },
  conflict: { label: "conflict", many: "conflicts", colour: "#8c564b" },
  vda_error: { label: "VDA error", many: "VDA errors", colour: "#e377c2" },
  command_failed: { label: "command failed", many: "commands failed", colour: "#17becf" },
};
export const KINDS = Object.keys(KIND_STYLE) as IncidentKind[];

export function isKind(v: string): v is IncidentKind {
  return (KINDS as string[]).includes(v);
}

/** A click seeks this long before an incident's start: the approach is on screen. */
export const LEAD_MS = 5000;

export function incidentSeek(i: Pick<Incident, "start_ms">): number {
  return i.start_ms - LEAD_MS;
}

/** What the server filters by (the area is applied here). */
export interface IncidentQuery {
  kinds: IncidentKind[];
  robot: string | null;
}

export function incidentsUrl(base: string, fromMs: number, toMs: number, q: IncidentQuery, limit: number): string {
  const p = new URLSearchParams({ from: String(Math.floor(fromMs)), to: String(Math.ceil(toMs)), limit: String(limit) });
  for (const k of q.kinds) p.append("kind", k);
  if (q.robot) p.set("robot", q.robot);
  return `${base}/api/v1/incidents?${p.toString()}`;
}

/** Whether an incident's place lies in the chunk box (no box: everywhere; no meta yet: kept). */
export function inArea(i: Pick<Incident, "x" | "y">, box: ChunkBox | null, meta: MapMeta | null): boolean {
  if (!box || !meta) return true;
  const c = chunkAt(meta, i.x, i.y);
  return !!c && c.row >= box.rowMin && c.row <= box.rowMax && c.column >= box.colMin && c.column <= box.colMax;
}

/** Whether an incident meets [from, to) as the API reads a window: begun before its end,
 * not ended before its start. */
export function meets(i: Pick<Incident, "start_ms" | "end_ms">, from: number, to: number): boolean {
  return i.start_ms < to && i.end_ms >= from;
}

/** Whether an incident passes what the server was asked to filter by. */
export function matchesQuery(i: Pick<Incident, "kind" | "robots">, q: IncidentQuery): boolean {
  return (!q.kinds.length || q.kinds.includes(i.kind)) && (!q.robot || i.robots.includes(q.robot));
}

/** The panel's list: what was read (and announced since), in the span and the area, by start. */
export function shownIncidents(items: Incident[], span: readonly [number, number], box: ChunkBox | null,
  meta: MapMeta | null): Incident[] {
  return items.filter((i) => meets(i, span[0], span[1]) && inArea(i, box, meta));
}

function byStart(a: Incident, b: Incident): number {
  return a.start_ms - b.start_ms || (a.kind < b.kind ? -1 : a.kind > b.kind ? 1 : 0) || (a.id < b.id ? -1 : a.id > b.id ? 1 : 0);
}

export function sortByStart(items: Incident[]): Incident[] {
  return [...items].sort(byStart);
}

/**
 * The list read with a live announcement applied: a finding replaces the incident of its
 * id (or joins the list when it meets the read window and the query), a retraction drops it.
 */
export function applyAnnouncement(items: Incident[], a: Pick<IncidentAnnouncement, "retracted" | "incident">,
  read: { from: number; to: number }, q: IncidentQuery): Incident[] {
  const rest = items.filter((i) => i.id !== a.incident.id);
  if (a.retracted || !meets(a.incident, read.from, read.to) || !matchesQuery(a.incident, q)) {
    return rest.length === items.length ? items : rest;
  }
  return sortByStart([...rest, a.incident]);
}

/** One bucket of the timeline's incident lane: how many of each kind begin in it. */
export interface LaneBucket {
  start_ms: number;
  end_ms: number;
  counts: Partial<Record<IncidentKind, number>>;
  total: number;
}

/**
 * The lane's buckets with incidents: [from, to) cut into `buckets` equal buckets, each
 * incident counted in the bucket of its start (one begun before the span, in the first).
 */
export function laneCounts(items: Pick<Incident, "kind" | "start_ms" | "end_ms">[], from: number, to: number,
  buckets: number): LaneBucket[] {
  const n = Math.max(1, Math.floor(buckets));
  const width = (to - from) / n;
  if (!(width > 0)) return [];
  const out = new Map<number, LaneBucket>();
  for (const i of items) {
    if (!meets(i, from, to)) continue;
    const k = Math.min(n - 1, Math.max(0, Math.floor((i.start_ms - from) / width)));
    let b = out.get(k);
    if (!b) out.set(k, (b = { start_ms: from + k * width, end_ms: from + (k + 1) * width, counts: {}, total: 0 }));
    b.counts[i.kind] = (b.counts[i.kind] ?? 0) + 1;
    b.total++;
  }
  return [...out.keys()].sort((a, b) => a - b).map((k) => out.get(k)!);
}

/** "2 near misses · 1 stuck" for a lane bucket's hover. */
export function laneText(b: LaneBucket): string {
  return KINDS.filter((k) => b.counts[k]).map((k) => `${b.counts[k]} ${b.counts[k] === 1 ? KIND_STYLE[k].label : KIND_STYLE[k].many}`)
    .join(" · ");
}

/**
 * The incident to step to (`dir` 1 next, -1 previous) in a list sorted by start: from the
 * picked one while the playhead is still where its pick left it (so incidents beginning at
 * the same instant are each visited), else from the playhead, by where a pick seeks.
 */
export function neighbourIncident(sorted: Incident[], pickedId: string | null, playhead: number, dir: 1 | -1): Incident | null {
  const at = pickedId === null ? -1 : sorted.findIndex((i) => i.id === pickedId);
  if (at >= 0 && incidentSeek(sorted[at]) === playhead) return sorted[at + dir] ?? null;
  if (dir > 0) return sorted.find((i) => incidentSeek(i) > playhead) ?? null;
  for (let k = sorted.length - 1; k >= 0; k--) if (incidentSeek(sorted[k]) < playhead) return sorted[k];
  return null;
}

/** What an incident's figure says: "0.42 m apart", "stuck 45 s", "silent 2 min 5 s", "lowest 12 %",
 * "inside 8 s", "3 chunk writes", "error 40 s", "waited 10 s". */
export function measureText(i: Pick<Incident, "kind" | "measure" | "ongoing">): string {
  const secs = (s: number) => (s < 120 ? `${Math.round(s)} s` : `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`);
  switch (i.kind) {
    case "near_miss": return `${i.measure.toFixed(2)} m apart`;
    case "stuck": return `stuck ${secs(i.measure)}${i.ongoing ? " so far" : ""}`;
    case "offline": return `silent ${secs(i.measure)}${i.ongoing ? " so far" : ""}`;
    case "battery_low": return `lowest ${Math.round(i.measure)} %`;
    case "zone_violation": return `inside ${secs(i.measure)}${i.ongoing ? " so far" : ""}`;
    case "conflict": return `${Math.round(i.measure)} chunk write${i.measure === 1 ? "" : "s"}`;
    case "vda_error": return `error ${secs(i.measure)}${i.ongoing ? " so far" : ""}`;
    case "command_failed": return `waited ${secs(i.measure)}`;
  }
}

/** The window a picked incident's trails cover: from before its lead to a little after it,
 * at most TRAIL_MAX_MS after its start (a silence may last hours). */
export const TRAIL_AROUND_MS = 30_000;
export const TRAIL_MAX_MS = 10 * 60_000;
export function trailWindow(i: Pick<Incident, "start_ms" | "end_ms">): [number, number] {
  return [i.start_ms - TRAIL_AROUND_MS, Math.min(i.end_ms, i.start_ms + TRAIL_MAX_MS) + TRAIL_AROUND_MS];
}
