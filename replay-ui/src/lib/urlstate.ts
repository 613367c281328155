/** What the address bar carries, so a link reopens the same moment, speed and view. */
import { isSpeed, type Speed } from "./clock";

export interface UrlState {
  live: boolean;
  t: number | null; // epoch ms
  speed: Speed;
  dir: 1 | -1;
  playing: boolean;
  view: { lat: number; lng: number; zoom: number } | null;
  follow: string | null;
}

export function parseUrlState(search: string): UrlState {
  const q = new URLSearchParams(search);
  const rawT = q.get("t");
  let t: number | null = null;
  if (rawT) {
    t = /^-?\d+$/.test(rawT) ? Number(rawT) : Date.parse(/[zZ]|[+-]\d\d:?\d\d$/.test(rawT) ? rawT : `${rawT}Z`);
    if (Number.isNaN(t)) t = null;
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
  };
}

export function formatUrlState(s: UrlState): string {
  const q = new URLSearchParams();
  if (s.live) q.set("live", "1");
  else if (s.t !== null) q.set("t", new Date(s.t).toISOString());
  q.set("speed", String(s.speed));
  if (s.dir < 0) q.set("dir", "-1");
  if (s.playing && !s.live) q.set("play", "1");
  if (s.view) q.set("view", `${s.view.zoom},${s.view.lat},${s.view.lng}`);
  if (s.follow) q.set("follow", s.follow);
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

/** The value of an <input type="datetime-local" step="1">, in UTC. */
export function toInputValue(ms: number): string {
  return new Date(ms).toISOString().slice(0, 19);
}

export function fromInputValue(v: string): number | null {
  const t = Date.parse(v.length === 16 ? `${v}:00Z` : `${v}Z`);
  return Number.isNaN(t) ? null : t;
}
