/**
 * The plot panel's series: battery (%), speed (m/s) and distance driven (m) over time for a
 * robot, from the API's aggregates of every stored pose per time bucket
 * (GET /api/v1/robots/{id}/track-buckets), so a figure is the same whichever zoom shows it:
 * a day's distance is its buckets' sum at any bucket size. Pure: the panel fetches the
 * buckets and draws these.
 */
import { batteryScales, levelPercent, type BatteryScales } from "./battery";
import type { TrackBuckets } from "./types";

/** Buckets asked for a plot `widthPx` wide: about one every three pixels. */
export function plotBuckets(widthPx: number): number {
  return Math.min(MAX_BUCKETS, Math.max(2, Math.round(widthPx / 3)));
}

/** The API's cap on buckets per read (api/routers/tracks.py). */
export const MAX_BUCKETS = 1000;

export interface RobotSeries {
  /** Each bucket's middle (within the window): where its battery and speed are drawn. */
  mid: number[];
  battery: (number | null)[]; // mean % over the bucket's poses
  batteryMin: (number | null)[]; // %
  batteryMax: (number | null)[]; // %
  speed: (number | null)[]; // m/s: the bucket's distance over the time its steps span
  bucketDistance: number[]; // m driven in each bucket
  /** The window's start, then each bucket's end (within the window): where distance is drawn. */
  edges: number[];
  distance: number[]; // m driven from the window's start to each edge
}

/** One robot's buckets as series: every bucket of the window, null where the robot has no
 * pose (a gap in the lines), the distance a running sum of the buckets'; battery in percent
 * on the robot's own scale, which the buckets' highest levels inform (lib/battery.ts). */
export function seriesOf(r: TrackBuckets, scales: BatteryScales = batteryScales): RobotSeries {
  const scale = scales.noted(r.robotId, ...r.buckets.map((b) => b.battery_max));
  const byStart = new Map(r.buckets.map((b) => [b.start_ms, b]));
  const out: RobotSeries = { mid: [], battery: [], batteryMin: [], batteryMax: [], speed: [], bucketDistance: [],
    edges: [r.from_ms], distance: [0] };
  let driven = 0;
  for (let start = Math.floor(r.from_ms / r.bucket_ms) * r.bucket_ms; start < r.to_ms; start += r.bucket_ms) {
    const lo = Math.max(start, r.from_ms);
    const hi = Math.min(start + r.bucket_ms, r.to_ms);
    const b = byStart.get(start);
    out.mid.push((lo + hi) / 2);
    out.battery.push(levelPercent(b?.battery_mean, scale));
    out.batteryMin.push(levelPercent(b?.battery_min, scale));
    out.batteryMax.push(levelPercent(b?.battery_max, scale));
    out.speed.push(b?.speed_mps ?? null);
    out.bucketDistance.push(b?.distance_m ?? 0);
    driven += b?.distance_m ?? 0;
    out.edges.push(hi);
    out.distance.push(driven);
  }
  return out;
}

/** The metres `s` shows driven in [from, to): between the distance line's points at those
 * instants (edges of its buckets; elsewhere the nearest edge within). */
export function drivenBetween(s: RobotSeries, from: number, to: number): number {
  const at = (t: number) => {
    let i = 0;
    while (i + 1 < s.edges.length && s.edges[i + 1] <= t) i++;
    return s.distance[i];
  };
  return at(to) - at(from);
}

export type SeriesKey = "battery" | "batteryMin" | "batteryMax" | "speed" | "distance";

/**
 * Several robots' series on one time axis (uPlot wants one x array): the union of their
 * instants, per robot and key (in that order) its value where it has one and undefined
 * elsewhere (bridged, not a gap; a gap is null).
 */
export function alignSeries(series: RobotSeries[], keys: readonly SeriesKey[]): [number[], ...(number | null | undefined)[][]] {
  const xsOf = (s: RobotSeries, k: SeriesKey) => (k === "distance" ? s.edges : s.mid);
  const xs = [...new Set(series.flatMap((s) => keys.flatMap((k) => xsOf(s, k))))].sort((a, b) => a - b);
  const index = new Map(xs.map((t, i) => [t, i]));
  const ys = series.flatMap((s) => keys.map((k) => {
    const col: (number | null | undefined)[] = new Array(xs.length).fill(undefined);
    xsOf(s, k).forEach((t, i) => (col[index.get(t)!] = s[k][i]));
    return col;
  }));
  return [xs, ...ys];
}

/** "1 s", "5 min", "1 h", "2 d": a bucket size as the panel names it. */
export function durationText(ms: number): string {
  const units: [number, string][] = [[86_400_000, "d"], [3_600_000, "h"], [60_000, "min"], [1000, "s"]];
  const [size, name] = units.find(([u]) => ms >= u && ms % u === 0) ?? [1, "ms"];
  return `${ms / size} ${name}`;
}

/** "850 m", "12.3 km". */
export function distanceText(m: number): string {
  return m < 1000 ? `${m.toFixed(0)} m` : `${(m / 1000).toFixed(m < 100_000 ? 2 : 1)} km`;
}
