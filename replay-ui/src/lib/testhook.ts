/**
 * window.__replay: what the browser tests and `mapservice bench ui` read and drive. Only
 * the test build holds it (`npm run build:test`, VITE_TEST_HOOK=1, into dist-test/, which
 * they serve): App.vue imports this module behind that build-time flag, so the production
 * bundle in dist/ has none of it. It only reads state and calls what the buttons call.
 */
import type { Ref, ShallowRef } from "vue";
import L from "leaflet";
import type { Speed } from "./clock";
import type { ReplayEngine } from "./engine";
import type { MapView } from "./mapview";
import type { RobotSeries } from "./plots";
import { fetchSpanMs } from "./buffer";
import { robotColour } from "./fleet";

export interface ReplayHookContext {
  engine: ReplayEngine;
  view: ShallowRef<MapView | null>;
  complete: () => boolean;
  /** The frame loop's animation frames and idle ticks, and the page's re-renders. */
  pace: () => { frames: number; idleTicks: number; renders: number };
  selected: Ref<string | null>;
  play: (dir: 1 | -1) => void;
  span: () => [number, number];
  /** The plot panel's series by robot and its step, or null when it is closed. */
  plots: () => { bucketMs: number; from: number; to: number; series: Map<string, RobotSeries> } | null;
  /** The x of an instant on the plots, css px from the left edge of their plotting area, or null. */
  plotX: (t: number) => number | null;
  timeline: () => unknown;
  /** The annotations read at the playhead, what the map draws of them, the edit tool. */
  annotations: () => unknown;
  /** The incidents panel's list (ids, as listed) and its pick. */
  incidents: () => { listed: string[]; picked: string | null };
  /** The heatmap's last read (its grid), whether one is under way or failed, and whether the
   * map shows its picture. */
  heatmap: () => { grid: unknown; loading: boolean; error: string | null; drawn: boolean };
}

export function exposeReplay(c: ReplayHookContext): void {
  const { engine, view } = c;
  (window as unknown as { __replay: unknown }).__replay = {
    engine,
    get playhead() { return engine.playhead; },
    get complete() { return c.complete(); },
    /** Animation frames run, idle ticks, page re-renders: while paused and at rest the first
     * and the last stand still (lib/framepace.ts). */
    get pace() { return c.pace(); },
    get seeking() { return engine.seeking; },
    get log() { return engine.state.log; },
    get seekTimes() { return engine.seekTimes; },
    get seekApiTimes() { return engine.seekApiTimes; },
    get frameTimes() { return engine.frameTimes; },
    get frameIntervals() { return engine.frameIntervals; },
    resetFrameStats: () => { engine.frameTimes = []; engine.frameIntervals = []; engine.stalls = []; },
    /** Every finished wait for the buffer while playing, then the current one if any (ms). */
    get stalls() { const now = engine.currentStallMs(); return now ? [...engine.stalls, now] : engine.stalls; },
    get buffering() { return engine.buffering; },
    get exactMapLoads() { return engine.exactMapLoads; },
    get mapExactAt() { return engine.mapExactAt; },
    get chunkStepMs() { return engine.buffer.chunkStepMs; },
    get windows() { return engine.buffer.windows; },
    /** Data time one fetch covers, in wall ms at the current speed (one buffer window). */
    get bufferWindowMs() { return fetchSpanMs(engine.clock.speed, engine.buffer.chunkStepMs > 0) / engine.clock.speed; },
    get applied() { return { forward: engine.state.applied, backward: engine.state.undone }; },
    clearCounts: () => engine.state.clearCounts(),
    /** false: fetch every chunk write at every speed (the benchmark's comparison run). */
    setCompaction: (on: boolean) => { engine.buffer.compact = on; },
    /** The map state as [row, column, ts_ms, robotId, content_hash], sorted by cell. */
    cells: () => [...engine.state.cells.values()]
      .map((x) => [x.row, x.column, x.ts_ms, x.robotId, x.content_hash])
      .sort((a, b) => (a[0] as number) - (b[0] as number) || (a[1] as number) - (b[1] as number)),
    get live() { return engine.clock.live; },
    get liveStatus() { return engine.live.status; },
    get meta() { return engine.meta; },
    get fetchedImages() { return engine.images.fetched; },
    seek: (t: number) => engine.seek(t),
    play: (speed: Speed, dir: 1 | -1 = 1) => { engine.setSpeed(speed); c.play(dir); },
    pause: () => engine.clock.pause(Date.now()),
    clearLog: () => { engine.state.log = []; },
    robots: () => engine.robots().map((r) => ({ robotId: r.robotId, x: r.x, y: r.y, ts_ms: r.pose.ts_ms, offline: r.offline })),
    chunkPixel: (row: number, col: number) => view.value?.chunks?.pixel(row, col) ?? null,
    screenPointOfPixel: (row: number, col: number) => view.value!.screenPointOfPixel(row, col),
    screenPointOfMetres: (x: number, y: number) => view.value!.screenPointOfMetres(x, y),
    drawnRobots: () => view.value?.drawnRobots() ?? [],
    fitGrid: () => view.value?.fitGrid(),
    clickRobot: (id: string) => { c.selected.value = id; },
    cell: (row: number, col: number) => engine.state.get(row * 65536 + col),
    view: () => view.value?.view() ?? null,
    drawnLabels: () => view.value?.robots.labels ?? [],
    /** The timeline's span the change feed lists and the plots show: [from, to). */
    span: c.span,
    /** The chunk the change feed outlines, as map-pixel bounds [[top, left], [bottom, right]], or null. */
    outlined: () => {
      const o = view.value?.changeOutline;
      if (!o || !view.value?.map.hasLayer(o)) return null;
      const b = o.getBounds();
      return [[-b.getNorth(), b.getWest()], [-b.getSouth(), b.getEast()]];
    },
    playing: () => engine.clock.playing,
    selected: () => c.selected.value,
    centerOnPixel: (row: number, col: number, zoom: number) =>
      view.value?.map.setView([-row, col], zoom, { animate: false }),
    /** The plotted series: {bucketMs, from and to (the read's), robots: {id: {colour, ...RobotSeries}}}, or null. */
    plots: () => {
      const p = c.plots();
      if (!p) return null;
      return { bucketMs: p.bucketMs, from: p.from, to: p.to,
        robots: Object.fromEntries([...p.series].map(([id, s]) => [id, { colour: robotColour(id), ...s }])) };
    },
    plotX: c.plotX,
    /** The selected robot's trail as drawn: its colour, how many points and runs (lib/trail.ts) it has. */
    trail: () => {
      const t = view.value?.trail;
      const runs = (t?.getLatLngs() ?? []) as unknown[][];
      return t ? { colour: t.options.color, weight: t.options.weight, points: runs.flat().length, runs: runs.length } : null;
    },
    timeline: c.timeline,
    annotations: c.annotations,
    /** The incidents panel's list and pick, and what the map shows of the pick: the robots
     * ringed, the trails drawn (robot, colour, points) and whether its place is marked. */
    incidents: () => {
      const v = view.value;
      const layers = v ? v.incidentLayer.getLayers() : [];
      const trails = layers.filter((l): l is L.Polyline => l instanceof L.Polyline).map((l) => ({
        colour: l.options.color, points: (l.getLatLngs() as unknown[][]).flat().length,
      }));
      return { ...c.incidents(), highlighted: v?.highlighted ?? [], trails, marked: layers.some((l) => l instanceof L.CircleMarker) };
    },
    heatmap: c.heatmap,
  };
}
