/**
 * The page's one requestAnimationFrame loop: the engine's frame, the map's chunks, robots,
 * info labels and conflict marks, the frame statistics; and the small reactive summary Vue
 * shows, refreshed every 200 ms (the engine and the map are plain objects, not reactive).
 */
import { onBeforeUnmount, reactive, type Ref, type ShallowRef } from "vue";
import { busyWaits } from "../lib/request";
import type { Speed } from "../lib/clock";
import type { ReplayEngine } from "../lib/engine";
import type { LayerToggles, MapView } from "../lib/mapview";
import type { Conflict } from "../lib/types";
import type { UrlState } from "../lib/urlstate";

const SUMMARY_MS = 200;
/** Info labels and conflict marks are drawn again at most this often. */
const INFO_MS = 500;
/** The frame statistics keep the last 1,000 to 2,000 frames. */
const FRAME_STATS_MAX = 2000;
/** Conflicts are read for an hour either side of the playhead, again once it moved ten minutes. */
const CONFLICTS_AROUND_MS = 3_600_000;
const CONFLICTS_REREAD_MS = 600_000;

export interface FrameLoopDeps {
  engine: ReplayEngine;
  view: ShallowRef<MapView | null>;
  toggles: LayerToggles;
  selected: Ref<string | null>;
  following: Ref<string | null>;
  /** The map's view from the address, applied once the map meta is there. */
  initialView: UrlState["view"];
  /** After each refresh of the summary. */
  onSummary: () => void;
}

export function useFrameLoop(d: FrameLoopDeps) {
  const { engine, view, toggles } = d;
  const ui = reactive({
    playhead: engine.playhead,
    now: Date.now(),
    playing: false,
    live: false,
    speed: 1 as Speed,
    dir: 1 as 1 | -1,
    buffering: false,
    seeking: false,
    complete: false,
    error: null as string | null,
    /** Some read waits for a busy server's Retry-After (lib/request.ts). */
    waiting: false,
    liveConnected: false,
    latencyMs: null as number | null,
    robots: 0,
    chunks: 0,
    fetched: 0,
  });
  let pendingView = d.initialView;
  let raf = 0;
  let lastFrame = 0;
  let lastSummary = 0;
  let lastInfo = 0;
  let lastRobotsKey = "";
  let conflicts: Conflict[] = [];
  let conflictsLoadedFor = 0;

  function loop(now: number) {
    raf = requestAnimationFrame(loop);
    const t0 = performance.now();
    engine.frame();
    const v = view.value;
    if (engine.meta && v) {
      if (v.meta !== engine.meta) v.setMeta(engine.meta, toggles, pendingView);
      pendingView = null;
      const complete = v.drawChunks() && !engine.seeking;
      if (complete) engine.seekFrameDrawn();
      ui.complete = complete && !engine.seekPendingFrame;
      // Robots move only when the playhead does or a live pose arrives; the layer itself
      // redraws on pan and zoom.
      const at = engine.clock.live ? Math.floor(engine.playhead / 1000) : engine.playhead;
      const key = `${at}:${engine.liveVersion}:${d.selected.value}:${d.following.value}`;
      if (key !== lastRobotsKey) {
        lastRobotsKey = key;
        const robots = engine.robots();
        v.selected = d.selected.value;
        v.updateRobots(robots);
        ui.robots = robots.length;
      }
      if (now - lastInfo > INFO_MS) {
        lastInfo = now;
        if (toggles.info) v.drawInfo(engine.playhead, toggles.infoMode);
        if (toggles.conflicts && engine.settled()) void updateConflicts(v);
      }
    }
    if (lastFrame) {
      engine.frameTimes.push(performance.now() - t0);
      engine.frameIntervals.push(now - lastFrame);
    }
    if (engine.frameTimes.length > FRAME_STATS_MAX) engine.frameTimes.splice(0, FRAME_STATS_MAX / 2);
    if (engine.frameIntervals.length > FRAME_STATS_MAX) engine.frameIntervals.splice(0, FRAME_STATS_MAX / 2);
    lastFrame = now;
    if (now - lastSummary > SUMMARY_MS) {
      lastSummary = now;
      summarise();
    }
  }

  function summarise() {
    const c = engine.clock;
    ui.playhead = engine.playhead;
    ui.now = Date.now();
    ui.playing = c.playing;
    ui.live = c.live;
    ui.speed = c.speed;
    ui.dir = c.direction;
    ui.buffering = engine.buffering;
    ui.seeking = engine.seeking;
    ui.error = engine.error;
    ui.waiting = busyWaits.count > 0;
    ui.liveConnected = engine.live.status.connected;
    ui.latencyMs = engine.live.status.latencyMs;
    ui.chunks = engine.state.cells.size;
    ui.fetched = engine.images.fetched;
    d.onSummary();
  }

  /** The map's conflict marks around the playhead. */
  async function updateConflicts(v: MapView) {
    const t = engine.playhead;
    if (Math.abs(t - conflictsLoadedFor) > CONFLICTS_REREAD_MS || conflictsLoadedFor === 0) {
      conflictsLoadedFor = t;
      try {
        conflicts = await engine.api.conflicts(t - CONFLICTS_AROUND_MS, t + CONFLICTS_AROUND_MS);
      } catch {
        conflicts = [];
      }
    }
    v.showConflicts(conflicts, t, CONFLICTS_AROUND_MS);
  }

  function start() {
    raf = requestAnimationFrame(loop);
  }

  /** After a layer toggle: the info labels and conflict marks at the next frame. */
  function redrawInfo() {
    lastInfo = 0;
  }

  onBeforeUnmount(() => {
    cancelAnimationFrame(raf);
    engine.live.stop();
  });

  return { ui, start, redrawInfo };
}
