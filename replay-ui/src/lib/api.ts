/**
 * The mapservice HTTP API as the replay needs it, with fallbacks: while an endpoint is
 * missing (404 from an older server), the same data comes from the older endpoints.
 */
import type { Source } from "./buffer";
import { parseBatch, type ChunkBatch } from "./chunkdecode";
import type { ChunkCell, Conflict, EventWindow, MapMeta, Pose, RobotAt, Timeline } from "./types";
import { authHeaders } from "./auth";
import type { TrackSample } from "./plots";
import type { Change } from "./changefeed";

export class ApiError extends Error {
  constructor(public status: number, message: string) {
    super(message);
  }
}

/** Answers that say "busy, come back" (the server's pools and per-client caps); retried
 * after their Retry-After (at most RETRY_CAP_MS), RETRIES times at most. */
const BUSY = new Set([429, 503]);
const RETRIES = 3;
const RETRY_CAP_MS = 5_000;

export async function fetchRetrying(url: string, sleep = (ms: number) => new Promise((r) => setTimeout(r, ms))): Promise<Response> {
  for (let attempt = 0; ; attempt++) {
    const r = await fetch(url, { headers: authHeaders() });
    if (!BUSY.has(r.status) || attempt >= RETRIES) return r;
    const seconds = Number(r.headers.get("Retry-After"));
    await sleep(Math.min(RETRY_CAP_MS, Number.isFinite(seconds) && seconds > 0 ? seconds * 1000 : 1000));
  }
}

export async function getJson<T>(url: string): Promise<T> {
  const r = await fetchRetrying(url);
  if (!r.ok) {
    let detail = r.statusText;
    try {
      detail = (await r.json()).detail ?? detail;
    } catch {
      /* not JSON */
    }
    throw new ApiError(r.status, `${url}: ${r.status} ${typeof detail === "string" ? detail : JSON.stringify(detail)}`);
  }
  return r.json() as Promise<T>;
}

const LIMIT = 100_000;
const DAY = 86_400_000;

export interface MapAt {
  at_ms: number;
  meta: MapMeta | null;
  chunks: ChunkCell[];
}

/** /api/v1/map as sent: `chunks` (layout=rows) or `fields` + `cells` (layout=compact). */
export interface MapAtWire {
  at_ms: number;
  meta: MapMeta | null;
  chunks?: ChunkCell[];
  fields?: string[];
  cells?: (string | number)[][];
}

/** Either layout of the map at T as ChunkCells. */
export function mapFromWire(w: MapAtWire): MapAt {
  if (!w.cells || !w.fields) return { at_ms: w.at_ms, meta: w.meta, chunks: w.chunks ?? [] };
  const at = (name: string) => {
    const i = w.fields!.indexOf(name);
    if (i < 0) throw new Error(`/api/v1/map: the compact layout lacks the field ${name}`);
    return i;
  };
  const [r, c, t, id, h] = ["row", "column", "ts_ms", "robotId", "content_hash"].map(at);
  return {
    at_ms: w.at_ms,
    meta: w.meta,
    chunks: w.cells.map((x) => ({ row: x[r] as number, column: x[c] as number, ts_ms: x[t] as number, robotId: x[id] as string, content_hash: x[h] as string })),
  };
}

export class Api implements Source {
  /** Endpoints found missing, so the fallback is used without asking again. */
  missing = new Set<string>();

  constructor(public base = "") {}

  chunkUrl(hash: string): string {
    return `${this.base}/api/v1/chunk-contents/${hash}?encoding=png`;
  }

  /** Many chunk pictures in one request (MessagePack); an ApiError 404/405 from an older server. */
  async chunkBatch(hashes: string[]): Promise<ChunkBatch> {
    const url = `${this.base}/api/v1/chunk-contents/batch`;
    const r = await fetch(url, { method: "POST", headers: { "Content-Type": "application/json", ...authHeaders() }, body: JSON.stringify({ hashes }) });
    if (!r.ok) throw new ApiError(r.status, `${url}: ${r.status} ${r.statusText}`);
    return parseBatch(await r.arrayBuffer());
  }

  /** The map at T, asked for in the compact layout (an older server answers with rows). */
  async map(atMs: number): Promise<MapAt> {
    return mapFromWire(await getJson<MapAtWire>(`${this.base}/api/v1/map?at=${Math.round(atMs)}&layout=compact`));
  }

  async mapAt(atMs: number): Promise<ChunkCell[]> {
    return (await this.map(atMs)).chunks;
  }

  async robotsAt(atMs: number): Promise<RobotAt[]> {
    return (await getJson<{ robots: RobotAt[] }>(`${this.base}/api/v1/robots?at=${Math.round(atMs)}`)).robots;
  }

  /** A replay window; `chunkStepMs` > 0 asks the server to compact chunk writes per bucket
   * (the fallback endpoints return every write, which is exact too). */
  async events(fromMs: number, toMs: number, stepMs: number, chunkStepMs = 0): Promise<EventWindow> {
    if (!this.missing.has("events")) {
      try {
        const compact = chunkStepMs > 0 ? `&chunk_step_ms=${chunkStepMs}` : "";
        return await getJson<EventWindow>(`${this.base}/api/v1/events?from=${fromMs}&to=${toMs}&step_ms=${stepMs}${compact}`);
      } catch (e) {
        if (!(e instanceof ApiError && e.status === 404 && this.isRouteMissing(e))) throw e;
        this.missing.add("events");
      }
    }
    return this.eventsFallback(fromMs, toMs, stepMs);
  }

  /** /chunk-events + /poses, downsampled here; truncated when either hit its limit. */
  async eventsFallback(fromMs: number, toMs: number, stepMs: number): Promise<EventWindow> {
    const [chunks, poses] = await Promise.all([
      getJson<ChunkCell[]>(`${this.base}/api/v1/chunk-events?from=${fromMs}&to=${toMs}&limit=${LIMIT}`),
      getJson<Pose[]>(`${this.base}/api/v1/poses?from=${fromMs}&to=${toMs}&limit=${LIMIT}`),
    ]);
    let truncated = chunks.length >= LIMIT;
    let sampled = downsample(poses, stepMs);
    if (poses.length >= LIMIT) {
      // Poses ran out first: the window is complete only up to the last pose returned.
      const lastPose = poses[poses.length - 1].ts_ms;
      truncated = true;
      const cut = chunks.findIndex((c) => c.ts_ms >= lastPose);
      const kept = cut < 0 ? chunks : chunks.slice(0, cut);
      // A last chunk write at the pose cut marks the complete prefix for `complete()`.
      return { from_ms: fromMs, to_ms: toMs, step_ms: stepMs, chunks: kept.concat(marker(lastPose)), poses: sampled.filter((p) => p.ts_ms < lastPose), truncated };
    }
    return { from_ms: fromMs, to_ms: toMs, step_ms: stepMs, chunks, poses: sampled, truncated };
  }

  async timeline(fromMs: number, toMs: number, buckets: number): Promise<Timeline | null> {
    if (this.missing.has("timeline")) return null;
    try {
      return await getJson<Timeline>(`${this.base}/api/v1/timeline?from=${Math.round(fromMs)}&to=${Math.round(toMs)}&buckets=${buckets}`);
    } catch (e) {
      if (e instanceof ApiError && e.status === 404) {
        this.missing.add("timeline");
        return null;
      }
      throw e;
    }
  }

  async conflicts(fromMs: number, toMs: number): Promise<Conflict[]> {
    if (this.missing.has("conflicts")) return [];
    try {
      const r = await getJson<Conflict[] | { conflicts: Conflict[] }>(
        `${this.base}/api/v1/conflicts?from=${Math.round(fromMs)}&to=${Math.round(Math.min(toMs, fromMs + DAY))}`);
      return Array.isArray(r) ? r : r.conflicts;
    } catch (e) {
      if (e instanceof ApiError && e.status === 404) {
        this.missing.add("conflicts");
        return [];
      }
      throw e;
    }
  }

  async track(robotId: string, fromMs: number, toMs: number, stepMs: number): Promise<Pose[]> {
    const f = Math.round(fromMs);
    const t = Math.round(toMs);
    if (!this.missing.has("track")) {
      try {
        const r = await getJson<{ points: { ts_ms: number; x: number; y: number; yaw: number }[] }>(
          `${this.base}/api/v1/robots/${encodeURIComponent(robotId)}/track?from=${f}&to=${t}&step_ms=${stepMs}`);
        return r.points.map((p) => ({
          robotId, ts_ms: p.ts_ms, position: [p.x, p.y, 0], orientation: [0, 0, Math.sin(p.yaw / 2), Math.cos(p.yaw / 2)],
          battery_level: null, charging: null, loaded: null, path: null,
        }));
      } catch (e) {
        if (!(e instanceof ApiError && e.status === 404 && this.isRouteMissing(e))) throw e;
        this.missing.add("track");
      }
    }
    return downsample(await getJson<Pose[]>(
      `${this.base}/api/v1/poses?from=${f}&to=${t}&robotId=${encodeURIComponent(robotId)}&limit=${LIMIT}`), stepMs);
  }

  /** Chunk writes in [from, to) (at most 100,000): the write times of an upload crossing
   * timeline buckets, so its writes leave the change bars where they are. */
  async chunkEvents(fromMs: number, toMs: number): Promise<{ ts_ms: number; robotId: string }[]> {
    return getJson<{ ts_ms: number; robotId: string }[]>(
      `${this.base}/api/v1/chunk-events?from=${Math.floor(fromMs)}&to=${Math.ceil(toMs)}&limit=100000`);
  }

  /** The map uploads in [from, to) (newest first, at most 1000), for the timeline's marks. */
  async uploads(fromMs: number, toMs: number): Promise<Change[]> {
    const r = await getJson<{ changes: Change[] }>(
      `${this.base}/api/v1/changes?kind=upload&limit=1000&from=${Math.round(fromMs)}&to=${Math.round(toMs)}`);
    return r.changes;
  }

  /** The robot's track with battery, the first pose of every `stepMs` in [from, to) (the plots). */
  async trackSamples(robotId: string, fromMs: number, toMs: number, stepMs: number): Promise<TrackSample[]> {
    const r = await getJson<{ points: TrackSample[] }>(`${this.base}/api/v1/robots/${encodeURIComponent(robotId)}`
      + `/track?from=${Math.round(fromMs)}&to=${Math.round(toMs)}&step_ms=${stepMs}`);
    return r.points;
  }

  private isRouteMissing(e: ApiError): boolean {
    return e.message.endsWith("Not Found");
  }
}

function marker(ts: number): ChunkCell {
  // Never applied: complete() drops writes at the last instant of a truncated window.
  return { ts_ms: ts, row: -1, column: -1, robotId: "", content_hash: "" };
}

/** At most one pose per robot per `stepMs` (the first in each step), as the API does. */
export function downsample(poses: Pose[], stepMs: number): Pose[] {
  if (stepMs <= 0) return poses;
  const seen = new Set<string>();
  const out: Pose[] = [];
  for (const p of poses) {
    const k = `${p.robotId}\u0000${Math.floor(p.ts_ms / stepMs)}`;
    if (!seen.has(k)) {
      seen.add(k);
      out.push(p);
    }
  }
  return out;
}
