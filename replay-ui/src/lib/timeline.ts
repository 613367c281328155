/**
 * What the timeline strip draws for each bucket of /api/v1/timeline: a bar for its chunk
 * changes, a conflict mark, and a thin band where robots reported (without the band an hour
 * of robots driving but no map change looked like an hour without history); and the
 * labelled time axis under it.
 *
 * Bars are on a square-root scale with a floor: a 187-chunk map upload next to buckets of
 * one or two changes left those under 1.5 px on a linear scale, invisible. Here a bucket
 * with one change is at least MIN_BAR_PX tall and its height still grows with its count.
 *
 * Pure: the strip passes its time-to-pixel mapping in.
 */
import type { Timeline, TimelineBucket } from "./types";

export const BAR_MAX_PX = 36;
export const MIN_BAR_PX = 3;

export interface StripMark {
  x: number;
  w: number;
  h: number; // the chunk-change bar's height
  conflicts: number;
  active: boolean; // at least one robot reported a pose in the bucket
}

export function barHeight(count: number, max: number): number {
  if (count <= 0) return 0;
  return MIN_BAR_PX + (BAR_MAX_PX - MIN_BAR_PX) * Math.sqrt(count / Math.max(1, max));
}

export function stripMarks(tl: Timeline, xOf: (t: number) => number): StripMark[] {
  const max = Math.max(1, ...tl.buckets.map((b) => b.chunk_changes));
  return tl.buckets.map((b) => ({
    x: xOf(b.start_ms),
    w: Math.max(1, xOf(b.start_ms + tl.bucket_ms) - xOf(b.start_ms) - 0.5),
    h: barHeight(b.chunk_changes, max),
    conflicts: b.conflicts,
    active: b.robots_active > 0,
  }));
}

/** The bucket holding `t`, or null outside the loaded timeline. */
export function bucketAt(tl: Timeline, t: number): TimelineBucket | null {
  const i = Math.floor((t - tl.from_ms) / tl.bucket_ms);
  const b = tl.buckets[i];
  return b && b.start_ms <= t && t < b.start_ms + tl.bucket_ms ? b : null;
}

/** "3 chunk changes · 1 conflict · 2 robots active" for the hover read-out. */
export function bucketText(b: TimelineBucket): string {
  const n = (k: number, one: string, many: string) => `${k} ${k === 1 ? one : many}`;
  return [n(b.chunk_changes, "chunk change", "chunk changes"), n(b.conflicts, "conflict", "conflicts"),
    n(b.robots_active, "robot active", "robots active")].join(" · ");
}

const SECOND = 1000;
const MINUTE = 60 * SECOND;
const HOUR = 60 * MINUTE;
const DAY = 24 * HOUR;
const STEPS = [SECOND, 5 * SECOND, 10 * SECOND, 30 * SECOND, MINUTE, 5 * MINUTE, 10 * MINUTE, 15 * MINUTE,
  30 * MINUTE, HOUR, 2 * HOUR, 3 * HOUR, 6 * HOUR, 12 * HOUR, DAY];

export interface Tick {
  t: number;
  label: string;
}

/** A label's width in px at an 11 px sans-serif font, from its length (a little wider than
 * measured: digits are 0.55 em there, colons and dashes less), where none can be measured. */
export function estimateLabelPx(label: string, fontPx = 11): number {
  return label.length * fontPx * 0.62;
}

/** Room left between two labels drawn centred on their ticks. */
export const LABEL_GAP_PX = 8;

function tickLabel(t: number, step: number, span: number): string {
  const iso = new Date(t).toISOString();
  const day = iso.slice(5, 10);
  const time = step < MINUTE ? iso.slice(11, 19) : iso.slice(11, 16);
  return step >= DAY || t % DAY === 0 || span > DAY ? `${day} ${time}` : time;
}

/**
 * Axis ticks on round UTC instants: the smallest round step (STEPS, then whole days) whose
 * ticks are at least `minGapPx` apart and whose labels, centred on their ticks at the
 * width `labelPx` gives them, never overlap. "14:05" within a day, "11-24 14:00" where the
 * span crosses days, "14:05:30" below a minute; a tick at midnight names its day.
 */
export function timeTicks(from: number, to: number, widthPx: number, minGapPx = 90,
  labelPx: (label: string) => number = estimateLabelPx): Tick[] {
  const span = Math.max(1, to - from);
  const pxPerMs = Math.max(1, widthPx) / span;
  const at = (step: number): Tick[] => {
    const ticks: Tick[] = [];
    for (let t = Math.ceil(from / step) * step; t <= to; t += step) ticks.push({ t, label: tickLabel(t, step, span) });
    return ticks;
  };
  const apart = (ticks: Tick[], step: number): boolean => {
    const widths = ticks.map((tk) => labelPx(tk.label));
    return widths.every((w, i) => i === 0 || step * pxPerMs >= (w + widths[i - 1]) / 2 + LABEL_GAP_PX);
  };
  for (const step of STEPS) {
    // A step too small for the gap is never laid out (a second over a week: 600k ticks).
    if (step * pxPerMs < minGapPx) continue;
    const ticks = at(step);
    if (apart(ticks, step)) return ticks;
  }
  for (let days = Math.max(1, Math.ceil(minGapPx / (DAY * pxPerMs))); ; days++) {
    const ticks = at(days * DAY);
    if (apart(ticks, days * DAY)) return ticks;
  }
}

/** A map upload as the timeline knows it (a `kind: "upload"` entry of the change feed). */
export interface UploadMark {
  ts_ms: number; // its first write
  end_ms: number; // its last write
  chunks: number;
  robot_id: string;
}

/**
 * Per bucket index, how many of the uploads' writes it holds: an upload inside one bucket
 * puts all its `chunks` there; one crossing buckets is counted from its writes' times,
 * `writeTimes(upload)` (its writer's writes from its first to its last: a run has no
 * other), which the strip reads only for such uploads.
 */
export async function uploadWritesPerBucket(tl: Timeline, uploads: UploadMark[],
  writeTimes: (u: UploadMark) => Promise<number[]>): Promise<Map<number, number>> {
  const out = new Map<number, number>();
  const add = (t: number, n: number) => {
    const i = Math.floor((t - tl.from_ms) / tl.bucket_ms);
    if (i >= 0 && i < tl.buckets.length) out.set(i, (out.get(i) ?? 0) + n);
  };
  for (const u of uploads) {
    if (Math.floor((u.ts_ms - tl.from_ms) / tl.bucket_ms) === Math.floor((u.end_ms - tl.from_ms) / tl.bucket_ms)) {
      add(u.ts_ms, u.chunks);
    } else {
      for (const t of await writeTimes(u)) add(t, 1);
    }
  }
  return out;
}

/** The timeline with the uploads' writes taken out of `chunk_changes`: an upload is its own
 * mark, never floor changes (nor the spike every other bar is scaled against). */
export function withoutUploads(tl: Timeline, perBucket: Map<number, number>): Timeline {
  if (!perBucket.size) return tl;
  return { ...tl, buckets: tl.buckets.map((b, i) => (perBucket.has(i)
    ? { ...b, chunk_changes: Math.max(0, b.chunk_changes - perBucket.get(i)!) } : b)) };
}

/** Where a click on a bucket's conflict mark seeks: just after the later write of the
 * bucket's first conflict (where the map holds it and the conflict box shows), or null. */
export function conflictSeek(conflicts: { ts_ms: number; seek_ms: number }[], startMs: number,
  bucketMs: number): number | null {
  const inBucket = conflicts.filter((c) => c.ts_ms >= startMs && c.ts_ms < startMs + bucketMs);
  if (!inBucket.length) return null;
  return inBucket.reduce((a, c) => (c.ts_ms < a.ts_ms ? c : a)).seek_ms;
}

/** The span the timeline shows first: the address's, else the hour up to `now`. */
export function initialSpan(fromAddress: readonly [number, number] | null | undefined, now: number): [number, number] {
  return fromAddress ? [fromAddress[0], fromAddress[1]] : [now - 3_600_000, now];
}

/**
 * The span the panels show, [from, to): the strip's view once it is mounted; before that
 * (panels rendered ahead of it read at their mount) the span the strip will start on, so
 * their first read is not of a span nobody asked for.
 */
export function shownSpan(strip: { viewFrom: number; viewTo: number } | null | undefined,
  fromAddress: readonly [number, number] | null | undefined, now: number): [number, number] {
  return strip ? [strip.viewFrom, strip.viewTo] : initialSpan(fromAddress, now);
}
