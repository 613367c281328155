/**
 * The prefetch buffer: one contiguous span [from, to) of history around the playhead.
 *
 * It holds every chunk write in the span (sorted) and the poses (one per robot per `stepMs`
 * at high speed). Above 60x the writes are compacted by the server (`chunkStepMs`): per
 * chunk and absolute bucket only the bucket's winner, so the map is exact at every bucket
 * boundary; no write is ever skipped at the client. The span grows ahead of the playhead by a look-ahead
 * sized to the speed and is trimmed behind it. Growing backwards fetches the map and robots
 * just before the new start, so every write in the buffer knows the cell it replaced.
 */
import { annotatePrev, cellKey, compareChanges } from "./mapstate";
import type { ChunkCell, ChunkChange, EventWindow, Pose, RobotAt } from "./types";

export interface Source {
  events(fromMs: number, toMs: number, stepMs: number, chunkStepMs?: number, signal?: AbortSignal): Promise<EventWindow>;
  mapAt(atMs: number): Promise<ChunkCell[]>;
  robotsAt(atMs: number): Promise<RobotAt[]>;
}

/**
 * Data time covered by one fetch: about two seconds of playback, 10 s to 6 h; up to a day
 * (the API's longest window) when the writes are compacted (a day of 20 min buckets is at
 * most 72 writes per chunk).
 */
export function fetchSpanMs(speed: number, compacted = chunkStepMs(speed) > 0): number {
  const cap = compacted ? 86_400_000 : 21_600_000;
  return Math.min(cap, Math.max(10_000, speed * 2_000));
}

/** What is kept behind the playhead: about two seconds of playback, 1 min to 6 h. */
export function keepBehindMs(speed: number): number {
  return Math.min(21_600_000, Math.max(60_000, speed * 2_000));
}

/** How far ahead of the playhead the buffer keeps: about four seconds of playback (at most
 * a day; two when compacted, so that a whole next window is always on the way). */
export function lookaheadMs(speed: number, compacted = chunkStepMs(speed) > 0): number {
  const cap = compacted ? 2 * 86_400_000 : 86_400_000;
  return Math.min(cap, Math.max(20_000, speed * 4_000));
}

/** Bucket sizes the compaction uses: whole minutes that divide an hour or a day. */
const CHUNK_STEPS = [60_000, 120_000, 300_000, 600_000, 1_200_000, 1_800_000];

/**
 * Chunk-write compaction for a speed: 0 (every write) up to 60x; above, the longest bucket
 * in CHUNK_STEPS not longer than the data one frame at 60 frames/s spans (3600x: 1 min,
 * 86400x: 20 min). A frame then never lands more than one bucket past an exact map, and
 * every change that could be seen for a frame is fetched.
 */
export function chunkStepMs(speed: number): number {
  if (speed <= 60) return 0;
  const perFrame = (speed * 1000) / 60;
  let step = CHUNK_STEPS[0];
  for (const s of CHUNK_STEPS) if (s <= perFrame) step = s;
  return step;
}

/** Pose downsampling for a speed: all poses up to 60x, about one per frame above. */
export function poseStepMs(speed: number): number {
  if (speed <= 60) return 0;
  // Whole minutes: the API answers those from per-minute keyframes.
  return Math.max(60_000, Math.round((speed * 16) / 60_000) * 60_000);
}

const MINUTE = 60_000;
/** The longest window /api/v1/events answers. */
const MAX_WINDOW_MS = 86_400_000;

export class EventBuffer {
  from: number;
  to: number;
  chunks: ChunkChange[] = [];
  tracks = new Map<string, Pose[]>();
  /** Each robot's latest pose before `from` (from the robots-at snapshot). */
  base = new Map<string, RobotAt>();
  stepMs: number;
  /** 0: every chunk write is buffered; > 0: the server's compaction bucket (ms). */
  chunkStepMs: number;
  /** When false, chunk writes are never compacted (the benchmark's "every write" run). */
  compact = true;
  /** Every window fetched since the last reset: [from, to, chunkStepMs] (to: as far as complete). */
  windows: [number, number, number][] = [];
  private inflight: Promise<void> | null = null;
  private generation = 0;
  /** Cancels the window reads of the generation a reset ended (nobody wants them). */
  private abort = new AbortController();
  maxChunks = 400_000;

  constructor(private source: Source, atMs: number, speed: number) {
    this.from = atMs + 1;
    this.to = atMs + 1;
    this.stepMs = poseStepMs(speed);
    this.chunkStepMs = chunkStepMs(speed);
  }

  /** Starts over at a seek: the caller has applied the map and robots at `atMs`. */
  reset(atMs: number, speed: number, robots: RobotAt[]): void {
    this.generation++;
    this.abort.abort();
    this.abort = new AbortController();
    this.inflight = null;
    this.from = atMs + 1;
    this.to = atMs + 1;
    this.chunks = [];
    this.tracks = new Map();
    this.base = new Map(robots.map((r) => [r.robotId, r]));
    this.stepMs = poseStepMs(speed);
    this.chunkStepMs = this.compact ? chunkStepMs(speed) : 0;
    this.windows = [];
  }

  /** True when every write with a < ts <= b (or b < ts <= a) is in the buffer. */
  covers(a: number, b: number): boolean {
    const lo = Math.min(a, b) + 1;
    const hi = Math.max(a, b) + 1;
    return lo >= this.from && hi <= this.to;
  }

  /** Fetches the next span needed ahead of the playhead, if any; one fetch at a time. */
  ensure(playhead: number, direction: 1 | -1, speed: number, nowMs: number, minMs: number): Promise<void> | null {
    if (this.inflight) return this.inflight;
    const ahead = lookaheadMs(speed, this.chunkStepMs > 0);
    const span = fetchSpanMs(speed, this.chunkStepMs > 0);
    // Window ends on whole buckets: no bucket is split between two windows (whose pieces
    // would each have a winner).
    const align = Math.max(MINUTE, this.chunkStepMs);
    let task: (() => Promise<void>) | null = null;
    if (direction > 0 && this.to < Math.min(playhead + ahead, nowMs + 1)) {
      const f = this.to;
      // Ends on a whole minute, so every later request starts on one (the API's fast path).
      let t = Math.ceil((f + span) / align) * align;
      if (t - f > MAX_WINDOW_MS) t = Math.floor((f + MAX_WINDOW_MS) / align) * align;
      t = Math.min(t, nowMs + 1);
      // Near now the windows get short: wait for two seconds of news unless the playhead
      // is about to run out, instead of asking once per round trip.
      const starving = this.to <= playhead + 1000;
      if (t > f && (starving || t - f >= Math.min(span, 2000))) task = () => this.extendForward(f, t);
    } else if (direction < 0 && this.from > Math.max(playhead - ahead, minMs)) {
      const t = this.from;
      let f = Math.floor((t - span) / align) * align;
      if (t - f > MAX_WINDOW_MS) f = Math.ceil((t - MAX_WINDOW_MS) / align) * align;
      f = Math.max(f, minMs);
      if (t > f) task = () => this.extendBackward(f, t);
    }
    if (!task) return null;
    const gen = this.generation;
    const p = task()
      .catch((err) => {
        if (gen === this.generation) throw err;
      })
      .finally(() => {
        if (gen === this.generation) this.inflight = null;
      });
    this.inflight = p;
    return p;
  }

  /** The playhead region [from, to) the last fetch covered up to (for "buffering" displays). */
  get busy(): boolean {
    return this.inflight !== null;
  }

  async extendForward(f: number, t: number): Promise<void> {
    const gen = this.generation;
    const w = await this.source.events(f, t, this.stepMs, this.chunkStepMs, this.abort.signal);
    if (gen !== this.generation || f !== this.to) return;
    const { chunks, poses, to } = complete(w, f, t);
    chunks.sort(compareChanges);
    // One by one: spreading a window's writes as arguments overflows the stack past ~120 k
    // (a 2 h window at 3600x holds 145 k compacted writes at 200 robots, 288 k in all).
    for (const c of chunks) this.chunks.push(c);
    this.logWindow(f, to);
    for (const p of poses) this.addPose(p, false);
    this.to = to;
  }

  async extendBackward(f: number, t: number): Promise<void> {
    const gen = this.generation;
    // The cells and robots as they were just before f, the base for the new writes' `prev`.
    const [w, before, robots] = await Promise.all([
      this.source.events(f, t, this.stepMs, this.chunkStepMs, this.abort.signal),
      this.source.mapAt(f - 1),
      this.source.robotsAt(f - 1),
    ]);
    if (gen !== this.generation || t !== this.from) return;
    const { chunks, poses, to } = complete(w, f, t);
    if (to < t) {
      // Truncated: keep only what was returned up to `to`, and fetch less next time.
      return this.extendBackward(f + Math.max(1, Math.floor((t - f) / 2)), t);
    }
    this.logWindow(f, to);
    chunks.sort(compareChanges);
    const baseCells = new Map(before.map((c) => [cellKey(c.row, c.column), c]));
    annotatePrev((k) => baseCells.get(k) ?? null, chunks);
    this.chunks = chunks.concat(this.chunks);
    for (const p of poses) this.addPose(p, true);
    this.base = new Map(robots.map((r) => [r.robotId, r]));
    this.from = f;
  }

  private logWindow(f: number, to: number): void {
    if (this.windows.length >= 10_000) this.windows.splice(0, 5_000);
    this.windows.push([f, to, this.chunkStepMs]);
  }

  private addPose(p: Pose, prepend: boolean): void {
    let track = this.tracks.get(p.robotId);
    if (!track) this.tracks.set(p.robotId, (track = []));
    if (prepend) track.unshift(p);
    else track.push(p);
  }

  /** Sorts tracks after bulk prepends (poses of one window arrive in time order). */
  normalise(): void {
    for (const track of this.tracks.values()) {
      for (let i = 1; i < track.length; i++) {
        if (track[i - 1].ts_ms > track[i].ts_ms) {
          track.sort((a, b) => a.ts_ms - b.ts_ms);
          break;
        }
      }
    }
  }

  /** Drops what lies far behind the playhead (relative to the direction of play). */
  trim(playhead: number, direction: 1 | -1, keepMs: number): void {
    if (direction > 0 && playhead - keepMs > this.from) {
      const cut = Math.min(playhead - keepMs, this.to);
      let i = 0;
      while (i < this.chunks.length && this.chunks[i].ts_ms < cut) i++;
      this.chunks = this.chunks.slice(i);
      for (const [id, track] of this.tracks) {
        let j = 0;
        while (j < track.length && track[j].ts_ms < cut) j++;
        if (j > 0) {
          this.base.set(id, track[j - 1]);
          this.tracks.set(id, track.slice(j));
        }
      }
      this.from = cut;
    } else if (direction < 0 && playhead + keepMs < this.to) {
      const cut = Math.max(playhead + keepMs, this.from);
      let i = this.chunks.length;
      while (i > 0 && this.chunks[i - 1].ts_ms >= cut) i--;
      this.chunks = this.chunks.slice(0, i);
      for (const [id, track] of this.tracks) {
        let j = track.length;
        while (j > 0 && track[j - 1].ts_ms >= cut) j--;
        this.tracks.set(id, track.slice(0, j));
      }
      this.to = cut;
    }
  }
}

/**
 * A window as far as it is complete. A truncated answer covers [from, to_ms) when the
 * server cut it there; otherwise (the fallback endpoints) up to, not including, the time
 * of its last chunk write, since writes sharing that instant may be cut.
 */
export function complete(w: EventWindow, f: number, t: number): { chunks: ChunkChange[]; poses: Pose[]; to: number } {
  if (!w.truncated) return { chunks: w.chunks.slice(), poses: w.poses.slice(), to: t };
  // /api/v1/events cuts a truncated answer itself and says where (to_ms < the asked end).
  const last = w.to_ms > f && w.to_ms < t ? w.to_ms : w.chunks.length ? w.chunks[w.chunks.length - 1].ts_ms : f;
  const to = Math.max(last, f + 1);
  const chunks = w.chunks.filter((c) => c.ts_ms < to);
  const poses = w.poses.filter((p) => p.ts_ms < to);
  return { chunks, poses, to };
}
