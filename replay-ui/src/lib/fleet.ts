/**
 * The fleet panel's rows and the robots' look: one colour per robot (marker ring, path,
 * list), battery in % (each robot on its own scale), speed from the track, the planned path's goal, and label placement
 * that never overlaps (a label that fits nowhere is left out; the list still names it).
 */
import { getJson } from "./api";
import { batteryScales, type BatteryScales } from "./battery";
import type { Pose } from "./types";

/** How far back the fleet panel reads poses for the speeds: two samples of a 1 Hz robot and slack. */
export const SPEED_WINDOW_MS = 10_000;

/** Every robot's poses of the SPEED_WINDOW_MS up to `t`, by robot (one request for the fleet). */
export async function recentTracks(base: string, t: number): Promise<Map<string, Pose[]>> {
  const url = `${base}/api/v1/poses?from=${Math.floor(t) - SPEED_WINDOW_MS}&to=${Math.floor(t) + 1}&limit=100000`;
  const tracks = new Map<string, Pose[]>();
  for (const p of await getJson<Pose[]>(url, "the robots' speeds")) {
    let track = tracks.get(p.robotId);
    if (!track) tracks.set(p.robotId, (track = []));
    track.push(p);
  }
  for (const track of tracks.values()) track.sort((a, b) => a.ts_ms - b.ts_ms);
  return tracks;
}

/** Adds `pose` to its robot's track in `tracks` (kept in time order) and drops the poses more
 * than `windowMs` older than the track's newest: the fleet panel's speeds while live, from
 * the live stream's poses (in any order: a late one is put in its place, a repeat ignored). */
export function addToTrack(tracks: Map<string, Pose[]>, pose: Pose, windowMs: number = SPEED_WINDOW_MS): void {
  let track = tracks.get(pose.robotId);
  if (!track) tracks.set(pose.robotId, (track = []));
  let i = track.length;
  while (i > 0 && track[i - 1].ts_ms > pose.ts_ms) i--;
  if (i > 0 && track[i - 1].ts_ms === pose.ts_ms) return;
  track.splice(i, 0, pose);
  const oldest = track[track.length - 1].ts_ms - windowMs;
  let drop = 0;
  while (track[drop].ts_ms < oldest) drop++;
  if (drop) track.splice(0, drop);
}

/** 24 colours apart enough to tell on a map: 12 hues 30 degrees apart, dark and light. */
const PALETTE = Array.from({ length: 24 }, (_, i) => `hsl(${((i * 7) % 12) * 30 + 5}, 75%, ${i < 12 ? 38 : 55}%)`);

/** A stable colour per robot id: a well mixed hash of the id picks one of PALETTE (ids
 * differing in one digit land far apart; more than 24 robots share colours). */
export function robotColour(id: string): string {
  let h = 2166136261;
  for (let i = 0; i < id.length; i++) h = Math.imul(h ^ id.charCodeAt(i), 16777619);
  h ^= h >>> 16;
  h = Math.imul(h, 0x85ebca6b);
  h ^= h >>> 13;
  h = Math.imul(h, 0xc2b2ae35);
  h ^= h >>> 16;
  return PALETTE[(h >>> 0) % PALETTE.length];
}

/** m/s between the latest sample at or before `t` and the one before it (null: no pair within 10 s). */
export function speedAt(track: Pose[] | undefined, t: number): number | null {
  if (!track || track.length < 2) return null;
  let i = track.length - 1;
  while (i >= 0 && track[i].ts_ms > t) i--;
  if (i < 1) return null;
  const a = track[i - 1];
  const b = track[i];
  const dt = (b.ts_ms - a.ts_ms) / 1000;
  if (dt <= 0 || dt > 10) return null;
  return Math.hypot(b.position[0] - a.position[0], b.position[1] - a.position[1]) / dt;
}

export function goalOf(path: [number, number][] | null | undefined): [number, number] | null {
  return path && path.length ? path[path.length - 1] : null;
}

export function flagText(v: boolean | string | null | undefined): string {
  if (v === null || v === undefined) return "?";
  if (typeof v === "boolean") return v ? "yes" : "no";
  return v;
}

export interface FleetRow {
  robotId: string;
  colour: string;
  online: boolean;
  batteryPct: number | null;
  charging: string;
  loaded: string;
  lastSeenMs: number;
  speed: number | null;
  goal: [number, number] | null;
  /** A VDA 5050 vehicle's errors and warnings at the playhead (composables/useVdaFacts). */
  errors?: { level: string; type: string; description: string }[];
  /** Its exact connection state (ONLINE, OFFLINE, CONNECTIONBROKEN), where one is known. */
  connection?: string;
}

export interface FleetRobot {
  robotId: string;
  pose: Pose;
  offline: boolean;
}

/** The fleet panel's rows, battery in percent on each robot's own scale (lib/battery.ts). */
export function fleetRows(robots: FleetRobot[], tracks: Map<string, Pose[]>, t: number, search: string,
  scales: BatteryScales = batteryScales): FleetRow[] {
  const q = search.trim().toLowerCase();
  return robots
    .filter((r) => !q || r.robotId.toLowerCase().includes(q))
    .map((r) => ({
      robotId: r.robotId,
      colour: robotColour(r.robotId),
      online: !r.offline,
      batteryPct: scales.percent(r.robotId, r.pose.battery_level),
      charging: flagText(r.pose.charging),
      loaded: flagText(r.pose.loaded),
      lastSeenMs: r.pose.ts_ms,
      speed: speedAt(tracks.get(r.robotId), t),
      goal: goalOf(r.pose.path),
    }))
    .sort((a, b) => a.robotId.localeCompare(b.robotId));
}

export interface Box {
  x: number;
  y: number;
  w: number;
  h: number;
}

function overlaps(a: Box, b: Box): boolean {
  return a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h;
}

/**
 * Places each label at the first of four spots around its marker (right, left, above,
 * below) that overlaps no label or marker placed before; null where none is free. Labels
 * are placed in the given order, so put the selected robot first.
 */
export function placeLabels(items: { x: number; y: number; w: number; h: number }[], radius: number): (Box | null)[] {
  const markers: Box[] = items.map((p) => ({ x: p.x - radius, y: p.y - radius, w: 2 * radius, h: 2 * radius }));
  const placed: Box[] = [];
  return items.map((p, i) => {
    const gap = radius + 3;
    const spots: Box[] = [
      { x: p.x + gap, y: p.y - p.h / 2, w: p.w, h: p.h },
      { x: p.x - gap - p.w, y: p.y - p.h / 2, w: p.w, h: p.h },
      { x: p.x - p.w / 2, y: p.y - gap - p.h, w: p.w, h: p.h },
      { x: p.x - p.w / 2, y: p.y + gap, w: p.w, h: p.h },
    ];
    for (const s of spots) {
      if (placed.some((b) => overlaps(b, s)) || markers.some((m, j) => j !== i && overlaps(m, s))) continue;
      placed.push(s);
      return s;
    }
    return null;
  });
}
