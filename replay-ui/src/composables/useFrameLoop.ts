/**
 * The page's one requestAnimationFrame loop: the engine's frame, the map's chunks, robots,
 * info labels and conflict marks, the frame statistics; and the small reactive summary Vue
 * shows, refreshed every 200 ms while frames run (the engine and the map are plain
 * objects, not reactive). It runs every animation frame only while something moves; else
 * an idle tick now and then, until an event wakes it (lib/framepace.ts decides which).
 */
import { onBeforeUnmount, reactive, watch, type Ref, type ShallowRef } from "vue";
import { busyWaits } from "../lib/request";
import { framePace, liveReadout } from "../lib/framepace";
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
    /** The playhead; live, its wall second (what the clock shows: not a render per frame). */
    playhead: engine.playhead,
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
  let idle: ReturnType<typeof setTimeout> | null = null;
  /** From start() until the page goes. */
  let running = false;
  /** Animation frames run, and idle ticks (for the tests: none while paused and at rest). */
  const pace = { frames: 0, idleTicks: 0 };
  let lastFrame = 0;
  let lastSummary = 0;
  let lastInfo = 0;
  let lastRobotsKey = "";
  let conflicts: Conflict[] = [];
  let conflictsLoadedFor = 0;

  /** Something changed (lib/framepace.ts): the next animation frame runs, whatever the pace. */
  function wake() {
    if (raf || !running) return;
    if (idle) clearTimeout(idle);
    idle = null;
    raf = requestAnimationFrame(loop);
  }

  /** After a frame or an idle tick: the next frame, or the idle tick. The one place that decides. */
  function next() {
    if (raf || !running) return;
    const v = view.value;
    const due = framePace({
      playback: engine.clock.playing && !engine.clock.live,
      seeking: engine.seeking,
      settled: engine.settled(),
      dirty: engine.state.dirty.size > 0 && !!v?.chunks,
    }, Date.now(), engine.clock.live);
    if (due === "frame") {
      raf = requestAnimationFrame(loop);
      return;
    }
    // The next frame after a rest is not a frame interval, and shows the summary at once.
    lastFrame = 0;
    lastSummary = 0;
    if (idle) clearTimeout(idle);
    idle = setTimeout(idleTick, due);
  }

  function loop(now: number) {
    raf = 0;
    pace.frames++;
    step(now, true);
    next();
  }

  function idleTick() {
    idle = null;
    pace.idleTicks++;
    step(performance.now(), false);
    next();
  }

  /** One step of the engine and the map; `framed`: in an animation frame (its times count). */
  function step(now: number, framed: boolean) {
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
    if (framed && lastFrame) {
      engine.frameTimes.push(performance.now() - t0);
      engine.frameIntervals.push(now - lastFrame);
    }
    if (engine.frameTimes.length > FRAME_STATS_MAX) engine.frameTimes.splice(0, FRAME_STATS_MAX / 2);
    if (engine.frameIntervals.length > FRAME_STATS_MAX) engine.frameIntervals.splice(0, FRAME_STATS_MAX / 2);
    lastFrame = framed ? now : 0;
    if (!framed || now - lastSummary > SUMMARY_MS) {
      lastSummary = now;
      summarise();
    }
  }

  /** The readouts. Vue re-renders what reads a field only when its value changes: live, the
   * playhead and the latency are written at the clock's resolution, a second. */
  function summarise() {
    const c = engine.clock;
    const second = c.live ? liveReadout(engine.playhead) : null;
    if (second === null || second !== ui.playhead) ui.latencyMs = engine.live.status.latencyMs;
    ui.playhead = second ?? engine.playhead;
    ui.playing = c.playing;
    ui.live = c.live;
    ui.speed = c.speed;
    ui.dir = c.direction;
    ui.buffering = engine.buffering;
    ui.seeking = engine.seeking;
    ui.error = engine.error;
    ui.waiting = busyWaits.count > 0;
    ui.liveConnected = engine.live.status.connected;
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

  /** Runs the loop; from now on whatever changes what is shown wakes it. */
  function start() {
    engine.onWake = wake;
    engine.images.afterBatch = wake;
    // A pan or zoom: the address keeps the view (the robots' canvas redraws itself).
    view.value?.map.on("moveend zoomend resize", wake);
    running = true;
    wake();
  }

  /** After a layer toggle: the info labels and conflict marks at the next frame. */
  function redrawInfo() {
    lastInfo = 0;
    wake();
  }

  // A robot selected or followed: drawn (and the map panned to it) at the next frame.
  watch([d.selected, d.following], wake);

  onBeforeUnmount(() => {
    running = false;
    cancelAnimationFrame(raf);
    if (idle) clearTimeout(idle);
    engine.live.stop();
  });

  return { ui, start, redrawInfo, pace };
}
