/**
 * The map as the replay shows it: chunk -> winning write, moved forwards and backwards.
 *
 * The map at T holds, per chunk, the write with the greatest (event time, robot id) among
 * writes with event time <= T (the server's rule). Moving the playhead from a to b applies
 * every write with a < ts <= b in that order; moving back undoes them in reverse order,
 * restoring each write's `prev` (the cell before it), so backwards is exact too.
 */
import type { ChunkCell, ChunkChange } from "./types";

export const cellKey = (row: number, column: number): number => row * 65536 + column;

/** Event-time order, ties broken by robot id as the server breaks them. */
export function compareChanges(a: ChunkCell, b: ChunkCell): number {
  if (a.ts_ms !== b.ts_ms) return a.ts_ms - b.ts_ms;
  return a.robotId < b.robotId ? -1 : a.robotId > b.robotId ? 1 : 0;
}

/** Writes with a < ts <= b, from a list sorted by `compareChanges` (binary search). */
export function changesBetween(sorted: ChunkChange[], a: number, b: number): ChunkChange[] {
  return sorted.slice(upperBound(sorted, a), upperBound(sorted, b));
}

/** First index whose ts_ms > t. */
export function upperBound(sorted: { ts_ms: number }[], t: number): number {
  let lo = 0;
  let hi = sorted.length;
  while (lo < hi) {
    const mid = (lo + hi) >> 1;
    if (sorted[mid].ts_ms <= t) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

/** Sets each write's `prev` from `base` (the cells just before the first write). */
export function annotatePrev(base: (key: number) => ChunkCell | null, sorted: ChunkChange[]): void {
  const last = new Map<number, ChunkCell | null>();
  for (const c of sorted) {
    const k = cellKey(c.row, c.column);
    c.prev = last.has(k) ? last.get(k)! : base(k);
    last.set(k, strip(c));
  }
}

function strip(c: ChunkCell): ChunkCell {
  return { row: c.row, column: c.column, ts_ms: c.ts_ms, robotId: c.robotId, content_hash: c.content_hash };
}

export interface AppliedChange {
  dir: 1 | -1;
  row: number;
  column: number;
  ts_ms: number;
  robotId: string;
  content_hash: string; // the hash the cell shows after this step
}

export class MapState {
  readonly cells = new Map<number, ChunkCell>();
  /** Cells changed since the renderer last looked. */
  readonly dirty = new Set<number>();
  /** Every applied write, in application order (read by the browser tests). */
  log: AppliedChange[] = [];
  logLimit = 500_000; // halved when reached: a week at 86400x would not fit
  /** Writes applied forwards and undone since the last `clearCounts` (never cut like the log). */
  applied = 0;
  undone = 0;

  clearCounts(): void {
    this.applied = 0;
    this.undone = 0;
  }

  reset(snapshot: ChunkCell[]): void {
    // Only cells whose picture changes need redrawing: a seek redraws what differs, not
    // the whole grid (the first frame after a seek stays short).
    const old = new Map(this.cells);
    this.cells.clear();
    for (const c of snapshot) {
      const k = cellKey(c.row, c.column);
      this.cells.set(k, strip(c));
      if (old.get(k)?.content_hash !== c.content_hash) this.dirty.add(k);
      old.delete(k);
    }
    for (const k of old.keys()) this.dirty.add(k);
  }

  get(key: number): ChunkCell | null {
    return this.cells.get(key) ?? null;
  }

  /** Applies writes in order; each one not yet annotated gets the cell it replaces as `prev`. */
  applyForward(sorted: ChunkChange[]): void {
    for (const c of sorted) {
      const k = cellKey(c.row, c.column);
      const cur = this.cells.get(k) ?? null;
      if (c.prev === undefined) c.prev = cur;
      // A late write older than what the cell shows is history, not the current state.
      if (cur === null || compareChanges(c, cur) >= 0) this.cells.set(k, strip(c));
      this.dirty.add(k);
      this.applied++;
      this.record(1, c, this.cells.get(k)!.content_hash);
    }
  }

  /** Undoes writes, given in forward order, newest first. */
  undo(sorted: ChunkChange[]): void {
    for (let i = sorted.length - 1; i >= 0; i--) {
      const c = sorted[i];
      if (c.prev === undefined) throw new Error(`write ${c.row}:${c.column}@${c.ts_ms} has no previous state`);
      const k = cellKey(c.row, c.column);
      if (c.prev === null) this.cells.delete(k);
      else this.cells.set(k, strip(c.prev));
      this.dirty.add(k);
      this.undone++;
      this.record(-1, c, c.prev?.content_hash ?? "");
    }
  }

  /** Moves from playhead a to b using the buffered writes. */
  move(sorted: ChunkChange[], a: number, b: number): number {
    if (b > a) {
      const fwd = changesBetween(sorted, a, b);
      this.applyForward(fwd);
      return fwd.length;
    }
    if (b < a) {
      const back = changesBetween(sorted, b, a);
      this.undo(back);
      return back.length;
    }
    return 0;
  }

  private record(dir: 1 | -1, c: ChunkCell, shown: string): void {
    if (this.log.length >= this.logLimit) this.log.splice(0, this.log.length >> 1);
    this.log.push({ dir, row: c.row, column: c.column, ts_ms: c.ts_ms, robotId: c.robotId, content_hash: shown });
  }
}
