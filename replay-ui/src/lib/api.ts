/**
 * The mapservice HTTP API as the replay needs it. The page is served by the API it reads
 * (same version), so every endpoint is there: a 404 is an error, never a reason to ask
 * another endpoint.
 */
import type { Source } from "./buffer";
import { parseBatch, type ChunkBatch } from "./chunkdecode";
import type { ChunkCell, Conflict, EventWindow, MapMeta, Pose, RobotAt, Timeline, TrackBuckets } from "./types";
import { ApiError, explainFailure, explainUnreachable, fetchRetrying, getJson, isAbort } from "./request";
import type { Change } from "./changefeed";

export { ApiError, fetchRetrying, getJson } from "./request";

const DAY = 86_400_000;

export interface MapAt {
  at_ms: number;
  meta: MapMeta | null;
  chunks: ChunkCell[];
}

/** /api/v1/map?layout=compact as sent: `fields` names the columns of each of `cells`. */
export interface MapAtWire {
  at_ms: number;
  meta: MapMeta | null;
  fields: string[];
  cells: (string | number)[][];
}

/** The compact map at T as ChunkCells, its columns read by name. */
export function mapFromWire(w: MapAtWire): MapAt {
  const at = (name: string) => {
    const i = w.fields.indexOf(name);
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
  constructor(public base = "") {}

  chunkUrl(hash: string): string {
    return `${this.base}/api/v1/chunk-contents/${hash}?encoding=png`;
  }

  /** Many chunk pictures in one request (MessagePack). */
  async chunkBatch(hashes: string[], signal?: AbortSignal): Promise<ChunkBatch> {
    const url = `${this.base}/api/v1/chunk-contents/batch`;
    let r: Response;
    try {
      r = await fetchRetrying(url, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ hashes }), signal });
    } catch (e) {
      if (isAbort(e) || signal?.aborted) throw e;
      throw new ApiError(0, explainUnreachable("the map's pictures"), String(e));
    }
    if (!r.ok) throw new ApiError(r.status, explainFailure("the map's pictures", r.status));
    return parseBatch(await r.arrayBuffer());
  }

  /** The map at T, asked for in the compact layout. */
  async map(atMs: number, signal?: AbortSignal): Promise<MapAt> {
    return mapFromWire(await getJson<MapAtWire>(`${this.base}/api/v1/map?at=${Math.round(atMs)}&layout=compact`, "the map", signal));
  }

  async mapAt(atMs: number): Promise<ChunkCell[]> {
    return (await this.map(atMs)).chunks;
  }

  async robotsAt(atMs: number, signal?: AbortSignal): Promise<RobotAt[]> {
    return (await getJson<{ robots: RobotAt[] }>(`${this.base}/api/v1/robots?at=${Math.round(atMs)}`, "the robots", signal)).robots;
  }

  /** A replay window; `chunkStepMs` > 0 asks the server to compact chunk writes per bucket. */
  async events(fromMs: number, toMs: number, stepMs: number, chunkStepMs = 0, signal?: AbortSignal): Promise<EventWindow> {
    const compact = chunkStepMs > 0 ? `&chunk_step_ms=${chunkStepMs}` : "";
    return getJson<EventWindow>(`${this.base}/api/v1/events?from=${fromMs}&to=${toMs}&step_ms=${stepMs}${compact}`, "the replay's next minutes", signal);
  }

  async timeline(fromMs: number, toMs: number, buckets: number, signal?: AbortSignal): Promise<Timeline> {
    return getJson<Timeline>(`${this.base}/api/v1/timeline?from=${Math.round(fromMs)}&to=${Math.round(toMs)}&buckets=${buckets}`, "the timeline", signal);
  }

  async conflicts(fromMs: number, toMs: number): Promise<Conflict[]> {
    const r = await getJson<{ conflicts: Conflict[] }>(
      `${this.base}/api/v1/conflicts?from=${Math.round(fromMs)}&to=${Math.round(Math.min(toMs, fromMs + DAY))}`, "the conflicts");
    return r.conflicts;
  }

  async track(robotId: string, fromMs: number, toMs: number, stepMs: number): Promise<Pose[]> {
    const r = await getJson<{ points: { ts_ms: number; x: number; y: number; yaw: number }[] }>(
      `${this.base}/api/v1/robots/${encodeURIComponent(robotId)}/track?from=${Math.round(fromMs)}&to=${Math.round(toMs)}&step_ms=${stepMs}`, `${robotId}'s trail`);
    return r.points.map((p) => ({
      robotId, ts_ms: p.ts_ms, position: [p.x, p.y, 0], orientation: [0, 0, Math.sin(p.yaw / 2), Math.cos(p.yaw / 2)],
      battery_level: null, charging: null, loaded: null, path: null,
    }));
  }

  /** Chunk writes in [from, to) (at most 100,000): the write times of an upload crossing
   * timeline buckets, so its writes leave the change bars where they are. */
  async chunkEvents(fromMs: number, toMs: number): Promise<{ ts_ms: number; robotId: string }[]> {
    return getJson<{ ts_ms: number; robotId: string }[]>(
      `${this.base}/api/v1/chunk-events?from=${Math.floor(fromMs)}&to=${Math.ceil(toMs)}&limit=100000`, "the upload's writes");
  }

  /** The map uploads in [from, to) (newest first, at most 1000), for the timeline's marks. */
  async uploads(fromMs: number, toMs: number, signal?: AbortSignal): Promise<Change[]> {
    const r = await getJson<{ changes: Change[] }>(
      `${this.base}/api/v1/changes?kind=upload&limit=1000&from=${Math.round(fromMs)}&to=${Math.round(toMs)}`, "the map uploads", signal);
    return r.changes;
  }

  /** The highest battery level robot `id` reported in [from, to) (null: none): the buckets'
   * highest over the fewest buckets the API gives (lib/battery.ts, to tell its scale). */
  async highestBatteryLevel(robotId: string, fromMs: number, toMs: number): Promise<number | null> {
    const levels = (await this.trackBuckets(robotId, fromMs, toMs, 2)).buckets
      .map((b) => b.battery_max).filter((v): v is number => v !== null);
    return levels.length ? Math.max(...levels) : null;
  }

  /** One robot's poses in [from, to) aggregated in at most `buckets` round buckets (the plots). */
  async trackBuckets(robotId: string, fromMs: number, toMs: number, buckets: number): Promise<TrackBuckets> {
    return getJson<TrackBuckets>(`${this.base}/api/v1/robots/${encodeURIComponent(robotId)}`
      + `/track-buckets?from=${Math.round(fromMs)}&to=${Math.round(toMs)}&buckets=${buckets}`, `${robotId}'s plots`);
  }
}
