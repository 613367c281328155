/**
 * The heatmap layer: which heatmap (kind and cell size) the address keeps, the API's read
 * of it (GET /api/v1/heatmap as a translucent PNG for the map, whose header carries the
 * grid's summary for the legend and the box), the legend's colour ramp (the PNG's: the API's
 * mapservice/core/heatmap_render.py draws with these stops) and the map's scale bar.
 */
import { oldestReadable } from "./retention";

export const HEATMAP_KINDS = ["occupancy", "dwell", "speed", "incidents"] as const;
export type HeatmapKind = (typeof HEATMAP_KINDS)[number];
/** The cell sizes offered, metres (the API takes any multiple of 0.5 m up to 20 m). */
export const HEATMAP_CELLS = [0.5, 1, 2, 5] as const;
export const DEFAULT_CELL_M = 0.5;

export const KIND_LABEL: Record<HeatmapKind, string> = {
  occupancy: "occupancy (time robots were there)",
  dwell: "dwell (time robots stood still)",
  speed: "mean speed",
  incidents: "incidents",
};

export interface HeatmapState {
  kind: HeatmapKind;
  cell: number;
}

/** The grid's summary the PNG answer carries in its SUMMARY_HEADER (the fields the page uses). */
export interface HeatmapSummary {
  kind: HeatmapKind;
  unit: string;
  from_ms: number;
  to_ms: number;
  cell_m: number;
  max: number;
  total: number;
  box: { i0: number; j0: number; columns: number; rows: number } | null;
}

/** The PNG answer's header holding its HeatmapSummary as JSON (api/routers/heatmaps.py). */
export const SUMMARY_HEADER = "X-Heatmap-Summary";

/** The summary of a PNG answer's headers; an error when it has none (a server too old for the page). */
export function summaryOf(headers: Headers): HeatmapSummary {
  const raw = headers.get(SUMMARY_HEADER);
  if (!raw) throw new Error(`the heatmap's picture came without its ${SUMMARY_HEADER} header: reload the page`);
  return JSON.parse(raw) as HeatmapSummary;
}

/** Low to high, as the PNG's ramp. */
export const RAMP: readonly [number, number, number][] = [
  [49, 54, 149], [69, 117, 180], [116, 196, 118], [254, 224, 75], [215, 48, 39],
];

export function isHeatmapKind(v: string): v is HeatmapKind {
  return (HEATMAP_KINDS as readonly string[]).includes(v);
}

/** "occupancy" or "dwell,2": the address's `heat` (the cell only when not the default). */
export function formatHeatmap(s: HeatmapState): string {
  return s.cell === DEFAULT_CELL_M ? s.kind : `${s.kind},${s.cell}`;
}

/** The address's `heat` back (null: no heatmap, or not one the API draws). */
export function parseHeatmap(v: string | null): HeatmapState | null {
  if (!v) return null;
  const [kind, cell] = v.split(",");
  const size = cell === undefined ? DEFAULT_CELL_M : Number(cell);
  const multiple = Math.round(size / 0.5);
  if (!isHeatmapKind(kind) || !(multiple >= 1 && multiple <= 40 && Math.abs(multiple * 0.5 - size) < 1e-9)) return null;
  return { kind, cell: size };
}

/** The read of a span's heatmap; its start no older than the history keeps at `now`. */
export function heatmapUrl(base: string, s: HeatmapState, span: readonly [number, number], now: number,
  format: "json" | "png" | "csv" = "json"): string {
  const from = Math.max(Math.round(span[0]), oldestReadable(now));
  const to = Math.max(from + 1, Math.round(span[1]));
  const q = new URLSearchParams({ kind: s.kind, from: String(from), to: String(to), cell: String(s.cell), format });
  return `${base}/api/v1/heatmap?${q.toString()}`;
}

/** The ramp's colour at a fraction in [0, 1], linearly between stops (as the PNG's). */
export function rampColour(fraction: number): string {
  const at = Math.min(1, Math.max(0, fraction)) * (RAMP.length - 1);
  const low = Math.min(Math.floor(at), RAMP.length - 2);
  const mix = at - low;
  const c = RAMP[low].map((v, k) => Math.round(v * (1 - mix) + RAMP[low + 1][k] * mix));
  return `rgb(${c[0]}, ${c[1]}, ${c[2]})`;
}

/** The legend's gradient, CSS. */
export function rampGradient(): string {
  return `linear-gradient(to right, ${RAMP.map((_, k) => rampColour(k / (RAMP.length - 1))).join(", ")})`;
}

/** A value with its unit as a reader wants it: seconds as "2 h 05 min", speeds in m/s. */
export function formatValue(v: number, unit: string): string {
  if (unit === "m/s") return `${v.toFixed(2)} m/s`;
  if (unit === "incidents") return `${Math.round(v)} ${Math.round(v) === 1 ? "incident" : "incidents"}`;
  const s = Math.round(v);
  const text = s < 60 ? `${s} s` : s < 3600 ? `${Math.floor(s / 60)} min ${String(s % 60).padStart(2, "0")} s`
    : `${Math.floor(s / 3600)} h ${String(Math.floor((s % 3600) / 60)).padStart(2, "0")} min`;
  return unit === "robot-seconds" ? `${text} (robot time)` : text;
}

/** The scale bar: the longest round length (1, 2 or 5 times a power of ten metres) no
 * longer than `maxPx` screen pixels, and its length on screen. */
export function scaleBar(metresPerPx: number, maxPx = 120): { metres: number; px: number; label: string } {
  const most = metresPerPx * maxPx;
  const power = 10 ** Math.floor(Math.log10(most));
  const metres = [5, 2, 1].map((m) => m * power).find((m) => m <= most) ?? power;
  const label = metres >= 1000 ? `${metres / 1000} km` : metres >= 1 ? `${metres} m` : `${Math.round(metres * 100)} cm`;
  return { metres, px: metres / metresPerPx, label };
}
