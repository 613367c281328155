/** What the address bar carries, so a link reopens the same moment, speed and view. */
import { isSpeed, type Speed } from "./clock";
import { formatHeatmap, parseHeatmap, type HeatmapState } from "./heatmap";
import { oldestReadable } from "./retention";

export interface UrlState {
  live: boolean;
  t: number | null; // epoch ms
  speed: Speed;
  dir: 1 | -1;
  playing: boolean;
  view: { lat: number; lng: number; zoom: number } | null;
  follow: string | null;
  /** The layers shown (null: the defaults), the selected robot, the open side panels, and
   * the change feed's area (chunk rows/columns) and robot. */
  layers: LayerState | null;
  selected: string | null;
  panels: string[];
  area: [number, number, number, number] | null;
  changeRobot: string | null;
  /** The timeline's span [from, to) in epoch ms (null: the last hour), which the change feed
   * lists and the plots show; and the robots plotted. */
  span: [number, number] | null;
  plot: string[];
  /** The incidents panel's filters (kinds: none is every kind; its robot) and the incident
   * picked in it (its id). */
  incidentKinds: string[];
  incidentRobot: string | null;
  incident: string | null;
  /** The heatmap over the floor (its kind and cell size; null: none), of the timeline's span. */
  heatmap: HeatmapState | null;
  /** What was wrong with the address's `t`, to tell the user (null: nothing). */
  tProblem: string | null;
}

export interface LayerState {
  names: boolean;
  battery: boolean;
  paths: boolean;
  borders: boolean;
  info: boolean;
  infoMode: "age" | "writer";
  conflicts: boolean;
  annotations: boolean;
}

const LAYER_NAMES = ["names", "battery", "paths", "borders", "info", "conflicts", "annotations"] as const;

/** "names,paths,info-writer": the layers that are on (the chunk info layer with its mode). */
export function formatLayers(l: LayerState): string {
  return LAYER_NAMES.filter((n) => l[n]).map((n) => (n === "info" ? `info-${l.infoMode}` : n)).join(",");
}

export function parseLayers(v: string): LayerState {
  const on = new Set(v.split(",").filter(Boolean));
  const info = on.has("info-age") || on.has("info-writer") || on.has("info");
  return {
    names: on.has("names"), battery: on.has("battery"), paths: on.has("paths"), borders: on.has("borders"),
    info, infoMode: on.has("info-writer") ? "writer" : "age", conflicts: on.has("conflicts"),
    annotations: on.has("annotations"),
  };
}

export function parseUrlState(search: string): UrlState {
  const q = new URLSearchParams(search);
  const rawT = q.get("t");
  let t: number | null = null;
  let tProblem: string | null = null;
  if (rawT) {
    t = /^-?\d+$/.test(rawT) ? Number(rawT) : Date.parse(/[zZ]|[+-]\d\d:?\d\d$/.test(rawT) ? rawT : `${rawT}Z`);
    if (Number.isNaN(t)) {
      t = null;
      tProblem = `the link's time t=${rawT} is not a time (use UTC like 2026-11-21T10:00:00Z or epoch milliseconds); showing live`;
    }
  }
  const s = Number(q.get("speed") ?? "1");
  let view: UrlState["view"] = null;
  const v = q.get("view")?.split(",").map(Number);
  if (v && v.length === 3 && v.every((n) => Number.isFinite(n))) view = { zoom: v[0], lat: v[1], lng: v[2] };
  return {
    live: q.get("live") === "1" || (t === null && q.get("live") !== "0"),
    t,
    speed: isSpeed(s) ? s : 1,
    dir: q.get("dir") === "-1" ? -1 : 1,
    playing: q.get("play") === "1",
    view,
    follow: q.get("follow"),
    layers: q.has("layers") ? parseLayers(q.get("layers") ?? "") : null,
    selected: q.get("sel"),
    panels: (q.get("panels") ?? "").split(",").filter((p) => (PANELS as readonly string[]).includes(p)),
    area: parseArea(q.get("area")),
    changeRobot: q.get("crobot"),
    span: parseSpan(q.get("span")),
    plot: (q.get("plot") ?? "").split(",").filter(Boolean),
    incidentKinds: (q.get("ikind") ?? "").split(",").filter(Boolean),
    incidentRobot: q.get("irobot"),
    incident: q.get("inc"),
    heatmap: parseHeatmap(q.get("heat")),
    tProblem,
  };
}

/** The side panels a link can open. */
export const PANELS = ["changes", "fleet", "conflicts", "plots", "annotations", "incidents"] as const;

/** "2026-11-24T13:00:00Z,2026-11-24T14:00:00Z" (or epoch ms): a span of at least a second. */
function parseSpan(v: string | null): [number, number] | null {
  const ends = v?.split(",").map((x) => (/^\d+$/.test(x) ? Number(x) : Date.parse(x)));
  return ends && ends.length === 2 && ends.every(Number.isFinite) && ends[1] - ends[0] >= 1000
    ? (ends as [number, number]) : null;
}

function parseArea(v: string | null): [number, number, number, number] | null {
  const a = v?.split(",").map(Number);
  return a && a.length === 4 && a.every((n) => Number.isInteger(n) && n >= 0) && a[0] <= a[1] && a[2] <= a[3]
    ? (a as [number, number, number, number]) : null;
}

/**
 * A `t` outside what the history keeps cannot be shown as asked: the nearest instant that
 * can, and what to tell the user (null when `t` is fine).
 */
export function clampToRetention(t: number, now: number, retentionMs: number): { t: number; problem: string | null } {
  const oldest = oldestReadable(now, retentionMs);
  if (t < oldest) {
    return { t: oldest, problem: `the link's time ${formatUtc(t)} is older than the ${Math.round(retentionMs / 86_400_000)} days the history keeps; showing the oldest instant kept` };
  }
  if (t > now) return { t: now, problem: `the link's time ${formatUtc(t)} is in the future; showing now` };
  return { t, problem: null };
}

export function formatUrlState(s: Omit<UrlState, "tProblem">): string {
  const q = new URLSearchParams();
  if (s.live) q.set("live", "1");
  else if (s.t !== null) q.set("t", new Date(s.t).toISOString());
  // Live has no speed or direction: the link reopens live, not a replay speed.
  if (!s.live) q.set("speed", String(s.speed));
  if (s.dir < 0 && !s.live) q.set("dir", "-1");
  if (s.playing && !s.live) q.set("play", "1");
  if (s.view) q.set("view", `${s.view.zoom},${s.view.lat},${s.view.lng}`);
  if (s.follow) q.set("follow", s.follow);
  if (s.layers) q.set("layers", formatLayers(s.layers));
  if (s.selected) q.set("sel", s.selected);
  if (s.panels.length) q.set("panels", s.panels.join(","));
  if (s.area) q.set("area", s.area.join(","));
  if (s.changeRobot) q.set("crobot", s.changeRobot);
  if (s.span) q.set("span", s.span.map((t) => new Date(Math.round(t)).toISOString()).join(","));
  if (s.plot.length) q.set("plot", s.plot.join(","));
  if (s.incidentKinds.length) q.set("ikind", s.incidentKinds.join(","));
  if (s.incidentRobot) q.set("irobot", s.incidentRobot);
  if (s.incident) q.set("inc", s.incident);
  if (s.heatmap) q.set("heat", formatHeatmap(s.heatmap));
  return `?${q.toString()}`;
}

/** "2026-11-21 10:00:05 UTC". */
export function formatUtc(ms: number): string {
  return new Date(ms).toISOString().replace("T", " ").replace(/\.\d+Z$/, " UTC");
}

/** "3 h 12 min ago", "now". */
export function agoText(ms: number, now: number): string {
  const d = Math.max(0, Math.round((now - ms) / 1000));
  if (d < 2) return "now";
  const days = Math.floor(d / 86400);
  const h = Math.floor((d % 86400) / 3600);
  const m = Math.floor((d % 3600) / 60);
  const s = d % 60;
  const parts = days ? [`${days} d`, `${h} h`] : h ? [`${h} h`, `${m} min`] : m ? [`${m} min`, `${s} s`] : [`${s} s`];
  return `${parts.join(" ")} ago`;
}

/** How long until agoText(ms, now) reads otherwise (ms, at least 1): each second under an
 * hour, each minute under a day, each hour beyond ("now" until two seconds). */
export function agoChangesIn(ms: number, now: number): number {
  const d = Math.max(0, Math.round((now - ms) / 1000));
  const unit = d < 3600 ? 1 : d < 86400 ? 60 : 3600;
  const next = d < 2 ? 2 : (Math.floor(d / unit) + 1) * unit;
  // d turns to `next` half a second before it (agoText rounds).
  return Math.max(1, (next - 0.5) * 1000 - (now - ms));
}

/** The picker's text: "2026-11-21 10:00:05", 24-hour UTC (a native date-time input would
 * show the browser's locale, e.g. 12-hour AM/PM, beside the UTC clock). */
export function toInputValue(ms: number): string {
  return new Date(ms).toISOString().slice(0, 19).replace("T", " ");
}

/** What the picker accepts, said where it refuses something. */
export const PICKER_FORMATS = "a UTC time as 2026-11-24 14:00:00, 2026-11-24T14:00:00Z (the link's format, milliseconds allowed) or 2026-11-24 14:00";

/** The picker's text back to epoch ms (UTC): "YYYY-MM-DD HH:MM[:SS[.sss]]" with a space or
 * a "T", optionally ending in "Z" (the address's own format); null if not one. */
export function fromInputValue(v: string): number | null {
  const m = /^\s*(\d{4}-\d\d-\d\d)[ T](\d\d:\d\d)(:\d\d(?:\.\d{1,3})?)?\s*[zZ]?\s*$/.exec(v);
  if (!m) return null;
  const t = Date.parse(`${m[1]}T${m[2]}${m[3] ?? ":00"}Z`);
  return Number.isNaN(t) ? null : t;
}
