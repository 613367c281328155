/**
 * The change feed (GET /api/v1/changes) as the replay's panel needs it: the request, an area
 * drawn on the map as a chunk box, and the previous/next change from the playhead.
 */
import { getJson } from "./api";
import type { MapMeta } from "./types";

export interface Change {
  kind: "change" | "upload";
  ts_ms: number;
  row: number;
  column: number;
  robot_id: string;
  content_hash: string;
  previous_hash: string | null;
  chunks: number;
  end_ms: number;
}

export interface ChangePage {
  from_ms: number;
  to_ms: number;
  upload_rule: string;
  changes: Change[];
  next: string | null;
}

/** Chunks with rowMin <= row <= rowMax and colMin <= column <= colMax. */
export interface ChunkBox {
  rowMin: number;
  rowMax: number;
  colMin: number;
  colMax: number;
}

export interface ChangeFilter {
  robot: string | null;
  box: ChunkBox | null;
}

export function changesUrl(base: string, fromMs: number, toMs: number, f: ChangeFilter, limit = 200, before: string | null = null): string {
  const q = new URLSearchParams({ from: String(Math.floor(fromMs)), to: String(Math.ceil(toMs)), limit: String(limit) });
  if (f.robot) q.set("robot", f.robot);
  if (f.box) {
    q.set("row_min", String(f.box.rowMin));
    q.set("row_max", String(f.box.rowMax));
    q.set("col_min", String(f.box.colMin));
    q.set("col_max", String(f.box.colMax));
  }
  if (before) q.set("before", before);
  return `${base}/api/v1/changes?${q.toString()}`;
}

export async function fetchChanges(base: string, fromMs: number, toMs: number, f: ChangeFilter, limit = 200, before: string | null = null): Promise<ChangePage> {
  const url = changesUrl(base, fromMs, toMs, f, limit, before);
  return getJson<ChangePage>(url, "the change feed");
}

/** The chunk box two map pixels (corners of a drawn rectangle, any order) span, clipped to the grid; null outside it. */
export function boxOfPixels(meta: MapMeta, a: { row: number; col: number }, b: { row: number; col: number }): ChunkBox | null {
  const clip = (v: number, n: number) => Math.min(n - 1, Math.max(0, v));
  const r0 = Math.floor(Math.min(a.row, b.row) / meta.CHUNK_HEIGHT);
  const r1 = Math.floor(Math.max(a.row, b.row) / meta.CHUNK_HEIGHT);
  const c0 = Math.floor(Math.min(a.col, b.col) / meta.CHUNK_WIDTH);
  const c1 = Math.floor(Math.max(a.col, b.col) / meta.CHUNK_WIDTH);
  if (r1 < 0 || c1 < 0 || r0 >= meta.CHUNK_ROWS || c0 >= meta.CHUNK_COLS) return null;
  return { rowMin: clip(r0, meta.CHUNK_ROWS), rowMax: clip(r1, meta.CHUNK_ROWS), colMin: clip(c0, meta.CHUNK_COLS), colMax: clip(c1, meta.CHUNK_COLS) };
}

/** Where a click on a change seeks: just after it, so the map shows its result. */
export function seekTargetOf(c: Change): number {
  return (c.kind === "upload" ? c.end_ms : c.ts_ms) + 1;
}

/**
 * The change to step to from the playhead: `dir` 1 the first one after it, -1 the last one
 * whose result the playhead has passed (so repeated steps walk the list). `changes` in any order.
 */
export function neighbourChange(changes: Change[], playhead: number, dir: 1 | -1): Change | null {
  let best: Change | null = null;
  for (const c of changes) {
    const t = seekTargetOf(c);
    if (dir > 0 ? t > playhead && (!best || t < seekTargetOf(best)) : t < playhead && (!best || t > seekTargetOf(best))) best = c;
  }
  return best;
}

export function boxText(b: ChunkBox): string {
  return `rows ${b.rowMin}–${b.rowMax}, columns ${b.colMin}–${b.colMax}`;
}

/** What the change search needs of the timeline: its buckets' chunk writes. */
export interface WriteDensity {
  from_ms: number;
  to_ms: number;
  bucket_ms: number;
  buckets: { start_ms: number; chunk_changes: number }[];
}

/**
 * Where to look for the change next to the playhead, nearest first, from the timeline's
 * own counts: every change is a chunk write, so only buckets with writes can hold one.
 * Each range [from, to) reaches from the playhead to the end (dir 1) or from the start
 * (dir -1) of the 1st, 2nd, 4th, 8th… bucket with writes on that side: a first small read,
 * wider ones only where the nearest writes changed nothing. Without counts: the span's
 * side of the playhead at once.
 */
export function changeSearchRanges(tl: WriteDensity | null, span: readonly [number, number], playhead: number,
  dir: 1 | -1): [number, number][] {
  // A change is shown just after it (seekTargetOf): before the playhead means at least 1 ms before.
  const [lo, hi] = dir > 0 ? [Math.max(span[0], playhead), span[1]] : [span[0], Math.min(span[1], playhead - 1)];
  if (hi <= lo) return [];
  if (!tl) return [[lo, hi]];
  const ends = tl.buckets
    .filter((b) => b.chunk_changes > 0 && b.start_ms < hi && b.start_ms + tl.bucket_ms > lo)
    .map((b) => (dir > 0 ? Math.min(hi, b.start_ms + tl.bucket_ms) : Math.max(lo, b.start_ms)));
  if (dir < 0) ends.reverse();
  const out: [number, number][] = [];
  for (let k = 1; ; k *= 2) {
    const end = ends[Math.min(k, ends.length) - 1];
    if (end === undefined) break;
    out.push(dir > 0 ? [lo, end] : [end, hi]);
    if (k >= ends.length) break;
  }
  // Past the timeline's counts (a span it did not read yet): the rest at once.
  if ((dir > 0 && tl.to_ms < hi) || (dir < 0 && tl.from_ms > lo)) out.push([lo, hi]);
  return out;
}

/** One page of the change feed (newest first) of [from, to) older than `before`. */
export type ChangePageReader = (from: number, to: number, before: string | null) => Promise<ChangePage>;

/**
 * The change next to the playhead (what neighbourChange picks from a full list), read range
 * by range (changeSearchRanges) from the change feed, newest first: backwards, the first
 * page holding one has it; forwards, the oldest, paging back through the range.
 */
export async function findNeighbourChange(read: ChangePageReader, ranges: [number, number][], playhead: number,
  dir: 1 | -1): Promise<Change | null> {
  for (const [from, to] of ranges) {
    let before: string | null = null;
    let best: Change | null = null;
    do {
      const page = await read(from, to, before);
      best = neighbourChange(best ? [best, ...page.changes] : page.changes, playhead, dir);
      before = page.next;
    } while (before && !(dir < 0 && best));
    if (best) return best;
  }
  return null;
}
