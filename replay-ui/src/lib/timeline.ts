/**
 * What the timeline strip draws for each bucket of /api/v1/timeline: a bar for its chunk
 * changes (scaled to the busiest bucket), a conflict mark, and a thin band where robots
 * reported. Without the band an hour of robots driving but no map change looked like an
 * hour without history.
 *
 * Pure: the strip passes its time-to-pixel mapping in.
 */
import type { Timeline } from "./types";

export const BAR_MAX_PX = 36;

export interface StripMark {
  x: number;
  w: number;
  h: number; // the chunk-change bar's height
  conflicts: number;
  active: boolean; // at least one robot reported a pose in the bucket
}

export function stripMarks(tl: Timeline, xOf: (t: number) => number): StripMark[] {
  const max = Math.max(1, ...tl.buckets.map((b) => b.chunk_changes));
  return tl.buckets.map((b) => ({
    x: xOf(b.start_ms),
    w: Math.max(1, xOf(b.start_ms + tl.bucket_ms) - xOf(b.start_ms) - 0.5),
    h: (b.chunk_changes / max) * BAR_MAX_PX,
    conflicts: b.conflicts,
    active: b.robots_active > 0,
  }));
}
