/**
 * When the page's frame loop runs: every animation frame while something moves on its own
 * (playback, a seek's frame being completed and settled, map writes to draw), else one idle
 * tick now and then (the live clock's next second, a second while paused) that the events
 * changing something (a clock action, a seek, a live pose, a picture, a pan) cut short.
 * A page left open while nothing moves then costs next to nothing: no 60 frames a second
 * redrawing the same picture, no summary re-rendering the same readouts.
 *
 * Pure: the loop (composables/useFrameLoop.ts) passes the engine's state and the wall clock in.
 */

/** Paused, the idle tick: what is due by time alone (a failed seek's retry, the periodic
 * reads of the summary's panels) waits at most this long. */
export const IDLE_TICK_MS = 1000;
/** Live, the readouts (clock, latency) change once a second. */
export const LIVE_READOUT_MS = 1000;

export interface PaceState {
  /** The clock plays through the history (not live): the playhead moves every frame. */
  playback: boolean;
  /** A seek's reads are under way (its end wakes the loop; nothing to draw meanwhile). */
  seeking: boolean;
  /** engine.settled(): the seek's frame complete (or given up on) and the playhead at rest. */
  settled: boolean;
  /** Map writes not drawn yet. */
  dirty: boolean;
}

/** "frame": ask for the next animation frame; else how long until the idle tick (ms). */
export function framePace(s: PaceState, wallMs: number, live: boolean): "frame" | number {
  // Until a seek's frame is complete and the playhead settled (SETTLE_MS), the look-ahead,
  // exact robots and conflict marks wait on time passing: frames, so each is asked for on time.
  if (s.playback || s.dirty || (!s.seeking && !s.settled)) return "frame";
  // Live: at the next wall second, when the clock's readout changes.
  return live ? LIVE_READOUT_MS - (((wallMs % LIVE_READOUT_MS) + LIVE_READOUT_MS) % LIVE_READOUT_MS) : IDLE_TICK_MS;
}

/** What the summary shows as the live playhead: the wall second (its readout's resolution). */
export function liveReadout(playheadMs: number): number {
  return Math.floor(playheadMs / LIVE_READOUT_MS) * LIVE_READOUT_MS;
}
