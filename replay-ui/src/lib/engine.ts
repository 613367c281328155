/**
 * The replay engine: clock + buffer + map state + robots, advanced once per animation frame.
 *
 * A seek loads the map and robots at T in one go; then each frame moves the map from the
 * last shown instant to the clock's, applying (or undoing) every buffered write in between.
 * When the buffer does not reach the clock's instant yet, the playhead waits at the
 * buffer's edge ("buffering") instead of skipping writes. Above 60x the buffer holds the
 * server's per-bucket winners (exact at every bucket boundary); once the playhead rests
 * between two boundaries, the exact map at the playhead is loaded (a seek in place).
 */
import { Api } from "./api";
import { errorText, isAbort } from "./request";
import { chunkStepMs, EventBuffer, keepBehindMs, poseStepMs } from "./buffer";
import { PlaybackClock, type Speed } from "./clock";
import { ChunkImages } from "./images";
import { LiveConnection, liveUrl, type LiveMessage } from "./live";
import type { IncidentAnnouncement } from "./incidents";
import { MapState } from "./mapstate";
import { addToTrack } from "./fleet";
import { INTERPOLATE_MAX_SPEED, OFFLINE_AFTER_MS, poseAt, type PlacedPose } from "./poses";
import { oldestReadable } from "./retention";
import type { MapMeta, Pose, RobotAt } from "./types";

/**
 * While paused, what only matters later (the look-ahead window, conflict marks, the
 * timeline's density) is asked for once the playhead has stayed put this long after a
 * seek's first complete frame: a user scrubbing through the timeline would otherwise queue
 * those requests ahead of the next seek's map and robots on the server.
 */
export const SETTLE_MS = 300;
export const FRAME_WAIT_MAX_MS = 2000;
/** A seek that failed (the server stayed busy or unreachable beyond the reads' patience)
 * is tried again this long after, by itself: the page recovers without a reload. */
export const SEEK_RETRY_MS = 30_000;

export interface RobotView extends PlacedPose {
  robotId: string;
  status: RobotAt | Pose;
  /** Silent for longer than the server's offline threshold at the playhead. */
  offline: boolean;
}

export class ReplayEngine {
  readonly api: Api;
  readonly clock: PlaybackClock;
  readonly state = new MapState();
  readonly images: ChunkImages;
  readonly buffer: EventBuffer;
  meta: MapMeta | null = null;
  /** The instant the map currently shows. */
  playhead: number;
  seeking = false;
  buffering = false;
  error: string | null = null;
  /** Robot status from the last robots-at call (online, skew flags), by id. */
  robotInfo = new Map<string, RobotAt>();
  /**
   * The robots at the instant playback rests on, from the history itself (robots-at):
   * above 60x the buffer holds one pose per robot per step, so a sampled pose can be a
   * minute older than the robot's last report. Loaded by every seek and whenever the
   * playhead stops somewhere else (pause, step, the end of a buffer).
   */
  exactAt: { t: number; robots: Map<string, RobotAt> } | null = null;
  private exactLoading = -1;
  /** Live mode: latest pose per robot. */
  livePoses = new Map<string, Pose>();
  /** Each robot's live poses of the last seconds (fleet.ts SPEED_WINDOW_MS): the fleet
   * panel's speeds while live come from the stream, not from reading the poses again. */
  liveTracks = new Map<string, Pose[]>();
  /** Bumped by every live pose (the view redraws robots only when something moved). */
  liveVersion = 0;
  live: LiveConnection;
  seekStartedWall = 0;
  seekPendingFrame = false;
  /** performance.now() of the last seek's first complete frame (0: not drawn yet). */
  seekDrawnAt = 0;
  /** Seek-to-first-complete-frame durations (ms), for the benchmark. */
  seekTimes: number[] = [];
  /** Of which: the map and robots at T from the API (the rest is chunk pictures and drawing). */
  seekApiTimes: number[] = [];
  /** Script time of each animation frame (ms) and the time between frames. */
  frameTimes: number[] = [];
  frameIntervals: number[] = [];
  /** Playing, how long the playhead waited for the buffer each time it did (ms). */
  stalls: number[] = [];
  private stallStarted = 0;
  /** Seeks in place that replaced a compacted map with the exact one at a resting playhead. */
  exactMapLoads = 0;
  /** The instant the map state is known exact at (a seek's; -1 once compacted writes moved it). */
  mapExactAt = -1;
  /** The last playhead a seek in place was started for (a failed one is not retried per frame). */
  private exactMapTried = -1;
  private recordSeek = true;
  private seekGen = 0;
  /** Cancels the reads of a seek that a newer one superseded. */
  private seekAbort: AbortController | null = null;
  /** A seek that failed: its instant and when (the map is not known there; retried). */
  private failedSeek: { t: number; at: number } | null = null;
  private lastStepMs: number;
  onSeeked: () => void = () => {};
  /** Something changed that the page should show: a clock action, a seek's end, a live
   * pose or map write, the exact robots at rest, an error. The frame loop wakes
   * (lib/framepace.ts): while nothing moves it does not run every animation frame. */
  onWake: () => void = () => {};
  /** An incident announced on the live stream (the incidents panel merges it). */
  onIncident: (m: IncidentAnnouncement) => void = () => {};

  constructor(base = "", now = Date.now()) {
    this.api = new Api(base);
    this.clock = new PlaybackClock(now, now);
    this.clock.minMs = oldestReadable(now);
    this.playhead = now;
    this.images = new ChunkImages(this.api);
    this.buffer = new EventBuffer(this.api, now, 1);
    this.clock.onChange = () => this.onWake();
    this.lastStepMs = poseStepMs(1);
    this.live = new LiveConnection(liveUrl(location), (m) => this.onLive(m), (reconnect) => {
      // Whatever happened while disconnected is in the store: start again from now.
      if (reconnect) void this.seek(Date.now(), true);
    });
  }

  now(): number {
    return Date.now();
  }

  perfNow(): number {
    return performance.now();
  }

  /** The view drew the seek's first complete frame: records the seek time. */
  seekFrameDrawn(): void {
    if (!this.seekPendingFrame) return;
    this.seekPendingFrame = false;
    this.seekDrawnAt = this.perfNow();
    if (this.recordSeek) this.seekTimes.push(this.seekDrawnAt - this.seekStartedWall);
  }

  /** No seek under way, its frame drawn, and (unless playing) the playhead settled. */
  settled(): boolean {
    if (this.seeking) return false;
    const now = this.perfNow();
    // A frame that cannot complete (say, no tile in view) holds the rest back only so long.
    if (this.seekPendingFrame) return now - this.seekStartedWall >= FRAME_WAIT_MAX_MS;
    return this.clock.playing || this.clock.live || now - this.seekDrawnAt >= SETTLE_MS;
  }

  /** Shows the whole map and all robots at T at once. */
  async seek(t: number, keepLive = false, record = true): Promise<void> {
    const wall = this.now();
    this.recordSeek = record;
    this.clock.minMs = oldestReadable(wall);
    t = Math.round(Math.min(wall, Math.max(this.clock.minMs, t)));
    const gen = ++this.seekGen;
    this.seekAbort?.abort();
    const abort = (this.seekAbort = new AbortController());
    this.seeking = true;
    this.failedSeek = null;
    this.seekStartedWall = this.perfNow();
    this.seekDrawnAt = 0;
    if (!keepLive) {
      this.live.stop();
      this.clock.seek(t, wall);
      // The instant asked for, at once: the address keeps it while the map loads (or waits
      // for a busy server), never the instant shown before.
      this.playhead = t;
    }
    try {
      // Both at once; the pictures the map at T lacks are asked for (in a few batches, not
      // tile by tile) as soon as the map is here, while the robots may still be on the way.
      const map = this.api.map(t, abort.signal).then((m) => {
        if (gen === this.seekGen) this.images.requestMany(m.chunks.map((c) => c.content_hash));
        return m;
      });
      const [mapAt, robots] = await Promise.all([map, this.api.robotsAt(t, abort.signal)]);
      if (gen !== this.seekGen) return;
      if (record) this.seekApiTimes.push(this.perfNow() - this.seekStartedWall);
      this.meta = mapAt.meta ?? this.meta;
      this.state.reset(mapAt.chunks);
      this.mapExactAt = t;
      this.buffer.reset(t, this.clock.speed, robots);
      this.lastStepMs = this.buffer.stepMs;
      this.robotInfo = new Map(robots.map((r) => [r.robotId, r]));
      this.exactAt = { t, robots: new Map(this.robotInfo) };
      this.livePoses = new Map(robots.map((r) => [r.robotId, r]));
      this.liveTracks = new Map(robots.map((r) => [r.robotId, [r]]));
      this.liveVersion++;
      this.playhead = t;
      if (!keepLive) this.clock.hold(t, this.now());
      this.error = null;
      this.seekPendingFrame = true;
      const pending = this.pendingLive;
      this.pendingLive = [];
      this.seeking = false;
      for (const m of pending) this.onLive(m);
      this.onSeeked();
    } catch (e) {
      if (gen === this.seekGen && !isAbort(e)) {
        this.error = errorText(e);
        this.failedSeek = { t, at: this.now() };
      }
    } finally {
      if (gen === this.seekGen) this.seeking = false;
      this.onWake();
    }
  }

  async goLive(): Promise<void> {
    const wall = this.now();
    this.clock.goLive(wall);
    this.live.start();
    await this.seek(wall, true);
  }

  setSpeed(speed: Speed): void {
    this.clock.setSpeed(speed, this.now());
    // Coarser or finer pose sampling or write compaction needs a fresh buffer.
    const compaction = this.buffer.compact ? chunkStepMs(speed) : 0;
    if ((poseStepMs(speed) !== this.lastStepMs || compaction !== this.buffer.chunkStepMs) && !this.clock.live) {
      void this.seek(this.playhead, false, false);
    }
  }

  /** Advances to the clock's instant; called once per animation frame. */
  frame(): void {
    if (this.seeking) return;
    const wall = this.now();
    if (this.failedSeek) {
      // The map at the playhead is unknown: nothing to move; ask again in a while.
      if (wall - this.failedSeek.at >= SEEK_RETRY_MS) void this.seek(this.failedSeek.t, this.clock.live, false);
      return;
    }
    if (!this.meta) return;
    if (this.clock.live) {
      this.playhead = wall;
      this.buffering = false; // live follows the WebSocket, there is no buffer to wait for
      return;
    }
    let target = Math.round(this.clock.time(wall));
    const dir = this.clock.direction;
    this.buffering = false;
    if (!this.buffer.covers(this.playhead, target)) {
      const edge = target > this.playhead ? this.buffer.to - 1 : this.buffer.from - 1;
      target = target > this.playhead ? Math.max(this.playhead, edge) : Math.min(this.playhead, edge);
      this.clock.hold(target, wall);
      this.buffering = true;
    }
    this.countStall(this.buffering && this.clock.playing);
    if (this.clock.playing && dir > 0 && target >= wall - 1000) {
      // Caught up with now: live mode takes over (the WebSocket, not polling windows).
      // Only once the buffered writes reach now: after a stalled frame at 86400x the
      // clock alone may be past now while the writes in between are not applied yet.
      this.state.move(this.buffer.chunks, this.playhead, target);
      this.playhead = target;
      void this.goLive();
      return;
    }
    if (target !== this.playhead) {
      this.state.move(this.buffer.chunks, this.playhead, target);
      this.playhead = target;
    }
    // The look-ahead waits for the seek's first frame (and, paused, for the playhead to settle).
    if (!this.settled()) return;
    if (!this.clock.playing) {
      if (this.buffer.chunkStepMs > 0 && this.mapExactAt !== this.playhead && this.exactMapTried !== this.playhead) {
        this.exactMapTried = this.playhead;
        // Compacted writes are exact only at bucket boundaries: a seek in place loads the
        // map (and robots) at the resting playhead and a fresh buffer.
        this.exactMapLoads++;
        void this.seek(this.playhead, false, false);
        return;
      }
      this.loadExactRobots();
    }
    const before = this.buffer.chunks.length;
    const p = this.buffer.ensure(this.playhead, dir, this.clock.speed, wall, this.clock.minMs);
    if (p) {
      p.then(() => {
        this.buffer.normalise();
        // Prefetch the pictures of the writes just buffered, in playing order.
        const fresh = dir > 0 ? this.buffer.chunks.slice(before) : this.buffer.chunks.slice(0, this.buffer.chunks.length - before).reverse();
        this.images.requestMany(fresh.slice(0, 5000).map((c) => c.content_hash), false);
      }).catch((e) => {
        this.error = errorText(e);
        this.onWake();
      });
    }
    this.buffer.trim(this.playhead, dir, keepBehindMs(this.clock.speed));
  }

  /** How long the current wait for the buffer has lasted (0: not waiting). */
  currentStallMs(): number {
    return this.stallStarted ? this.perfNow() - this.stallStarted : 0;
  }

  /** Times each wait for the buffer while playing (`stalls`, ms). */
  private countStall(waiting: boolean): void {
    const now = this.perfNow();
    if (waiting && !this.stallStarted) this.stallStarted = now;
    else if (!waiting && this.stallStarted) {
      this.stalls.push(now - this.stallStarted);
      this.stallStarted = 0;
    }
  }

  /** Asks the history for the robots at the resting playhead, unless it has them. */
  private loadExactRobots(): void {
    const t = this.playhead;
    if (this.exactAt?.t === t || this.exactLoading === t) return;
    this.exactLoading = t;
    this.api.robotsAt(t).then((robots) => {
      if (this.playhead !== t || this.clock.playing || this.clock.live) return;
      this.exactAt = { t, robots: new Map(robots.map((r) => [r.robotId, r])) };
      for (const r of robots) this.robotInfo.set(r.robotId, r);
      this.liveVersion++; // the view redraws the robots
      this.onWake();
    }).catch((e) => {
      this.error = errorText(e);
      this.onWake();
    })
      .finally(() => { if (this.exactLoading === t) this.exactLoading = -1; });
  }

  /** Every robot at the playhead. */
  robots(): RobotView[] {
    const out: RobotView[] = [];
    if (this.clock.live) {
      for (const [id, p] of this.livePoses) {
        const offline = this.now() - p.ts_ms > OFFLINE_AFTER_MS;
        out.push({ robotId: id, status: this.robotInfo.get(id) ?? p, pose: p, x: p.position[0], y: p.position[1], yaw: null, offline });
      }
      return out;
    }
    const t = this.playhead;
    const exact = !this.clock.playing && this.exactAt?.t === t ? this.exactAt.robots : null;
    if (exact) {
      for (const [id, r] of exact) {
        const offline = r.online !== undefined ? !r.online : t - r.ts_ms > OFFLINE_AFTER_MS;
        out.push({ robotId: id, status: r, pose: r, x: r.position[0], y: r.position[1], yaw: null, offline });
      }
      return out;
    }
    // Sampled tracks (one pose per step) only show a robot's silence beyond the step.
    const silenceMs = OFFLINE_AFTER_MS + this.buffer.stepMs;
    const interpolate = this.clock.speed <= INTERPOLATE_MAX_SPEED;
    const ids = new Set([...this.buffer.base.keys(), ...this.buffer.tracks.keys()]);
    for (const id of ids) {
      const track = this.buffer.tracks.get(id);
      let placed = track ? poseAt(track, t, interpolate) : null;
      if (!placed) {
        const b = this.buffer.base.get(id);
        if (!b || b.ts_ms > t) continue;
        placed = { pose: b, x: b.position[0], y: b.position[1], yaw: null };
      }
      out.push({ robotId: id, status: placed.pose, ...placed, offline: t - placed.pose.ts_ms > silenceMs });
    }
    return out;
  }

  private pendingLive: LiveMessage[] = [];

  private onLive(m: LiveMessage): void {
    if (m.type === "incident") {
      // Not the floor's state: the incidents panel's, whatever the snapshot is doing.
      this.onIncident(m);
      return;
    }
    if (!this.clock.live) return;
    if (this.seeking) {
      // Arrived while the snapshot loads: applied right after it (older ones lose the tie).
      this.pendingLive.push(m);
      return;
    }
    if (m.type === "chunk") {
      this.state.applyForward([{ row: m.row, column: m.column, ts_ms: m.ts_ms, robotId: m.robotId, content_hash: m.content_hash }]);
      this.onWake();
    } else if (m.type === "pose") {
      addToTrack(this.liveTracks, m);
      const prev = this.livePoses.get(m.robotId);
      if (!prev || prev.ts_ms <= m.ts_ms) {
        this.livePoses.set(m.robotId, m);
        this.liveVersion++;
        this.onWake();
      }
    }
  }
}
