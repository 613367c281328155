/**
 * The plot panel's series: battery (%), speed (m/s) and distance driven (m) over time for a
 * robot, from its track downsampled by the API (the first pose of every step). Pure: the
 * panel fetches the track and draws these.
 */
import { batteryPercent } from "./fleet";

export interface TrackSample {
  ts_ms: number;
  x: number;
  y: number;
  battery_level: number | null;
}

export interface RobotSeries {
  ts: number[];
  battery: (number | null)[]; // %
  speed: (number | null)[]; // m/s, mean over the step before the sample
  distance: number[]; // m driven since the first sample of the window
}

/** Aim for about one sample per two pixels of plot, never below a pose a second. */
export function plotStepMs(fromMs: number, toMs: number, widthPx: number): number {
  const raw = (toMs - fromMs) / Math.max(50, widthPx / 2);
  return raw >= KEYFRAME_MS ? Math.ceil(raw / KEYFRAME_MS) * KEYFRAME_MS : Math.max(1000, Math.ceil(raw / 1000) * 1000);
}

/** The store keeps a pose a minute per robot apart (pose keyframes): a window starting on a
 * whole minute with a step of whole minutes is read from those, not from every pose. */
const KEYFRAME_MS = 60_000;

/** The track request for a span: its start (on a whole minute for steps of minutes) and step. */
export function plotWindow(fromMs: number, toMs: number, widthPx: number): { from: number; stepMs: number } {
  const stepMs = plotStepMs(fromMs, toMs, widthPx);
  const from = stepMs % KEYFRAME_MS === 0 ? Math.floor(fromMs / KEYFRAME_MS) * KEYFRAME_MS : Math.floor(fromMs);
  return { from, stepMs };
}

/** A gap longer than this between samples means the robot was silent: no speed across it. */
export function gapMs(stepMs: number): number {
  return Math.max(10_000, 3 * stepMs);
}

export function seriesOf(points: TrackSample[], stepMs: number): RobotSeries {
  const out: RobotSeries = { ts: [], battery: [], speed: [], distance: [] };
  let dist = 0;
  points.forEach((p, i) => {
    const prev = i > 0 ? points[i - 1] : null;
    let speed: number | null = null;
    if (prev) {
      const d = Math.hypot(p.x - prev.x, p.y - prev.y);
      const dt = (p.ts_ms - prev.ts_ms) / 1000;
      if (dt > 0 && p.ts_ms - prev.ts_ms <= gapMs(stepMs)) speed = d / dt;
      dist += d;
    }
    out.ts.push(p.ts_ms);
    out.battery.push(batteryPercent(p.battery_level));
    out.speed.push(speed);
    out.distance.push(dist);
  });
  return out;
}

/**
 * Several robots' series on one time axis (uPlot wants one x array): the union of their
 * sample times, each robot's value where it has a sample and null elsewhere.
 */
export function alignSeries(series: RobotSeries[], key: "battery" | "speed" | "distance"): [number[], ...(number | null | undefined)[][]] {
  const xs = [...new Set(series.flatMap((s) => s.ts))].sort((a, b) => a - b);
  const index = new Map(xs.map((t, i) => [t, i]));
  const ys = series.map((s) => {
    const col: (number | null | undefined)[] = new Array(xs.length).fill(undefined);
    s.ts.forEach((t, i) => (col[index.get(t)!] = s[key][i]));
    return col;
  });
  return [xs, ...ys];
}
