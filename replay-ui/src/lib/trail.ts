/**
 * The selected robot's trail as drawn: its track cut into runs where it could not have
 * driven from one point to the next (a jump: a robot placed elsewhere, a gap in its reports),
 * so no straight line is drawn across the floor between them; and none at all while playing
 * faster than a minute a second, where ten minutes of track pass in a tenth of a second and
 * the one read last lies far behind the robot.
 *
 * Pure.
 */

/** Faster than any floor robot drives (m/s): a step implying more is a jump. */
export const TRAIL_MAX_SPEED = 3;
/** A gap in the reports longer than this (ms) cuts the trail too: where it went between is unknown. */
export const TRAIL_MAX_GAP_MS = 60_000;
/** Above this speed the trail is not drawn while playing. */
export const TRAIL_MAX_REPLAY_SPEED = 60;

export interface TrailPoint {
  ts_ms: number;
  x: number;
  y: number;
}

/** The runs of the track (in time order) that a robot drove, each of two points or more. */
export function trailRuns(points: TrailPoint[]): TrailPoint[][] {
  const runs: TrailPoint[][] = [];
  let run: TrailPoint[] = [];
  for (const p of points) {
    const q = run[run.length - 1];
    if (q) {
      const dt = p.ts_ms - q.ts_ms;
      const d = Math.hypot(p.x - q.x, p.y - q.y);
      const jump = dt <= 0 ? d > 0 : dt > TRAIL_MAX_GAP_MS || d / (dt / 1000) > TRAIL_MAX_SPEED;
      if (jump) {
        if (run.length > 1) runs.push(run);
        run = [];
      }
    }
    run.push(p);
  }
  if (run.length > 1) runs.push(run);
  return runs;
}

/** Whether a trail is drawn at this replay state. */
export function trailShown(playing: boolean, live: boolean, speed: number): boolean {
  return live || !playing || speed <= TRAIL_MAX_REPLAY_SPEED;
}
