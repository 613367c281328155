/**
 * The playback clock: where the playhead is at a given wall-clock instant.
 *
 * Pure: the wall clock is passed in, so tests drive it. Time runs at `speed` times real
 * time, forwards or backwards, clamped to [minMs, now]. Live mode pins the playhead to now.
 */

export const SPEEDS = [1, 2, 4, 8, 60, 3600, 86400] as const;
export type Speed = (typeof SPEEDS)[number];

export function isSpeed(v: number): v is Speed {
  return (SPEEDS as readonly number[]).includes(v);
}

/** How far one press of "step" moves at a speed: one second of wall time's worth, at most 1 h. */
export function stepMs(speed: number): number {
  return Math.min(3_600_000, Math.max(1000, speed * 1000));
}

export interface ClockState {
  timeMs: number;
  speed: Speed;
  direction: 1 | -1;
  playing: boolean;
  live: boolean;
}

export class PlaybackClock {
  private anchorTime: number;
  private anchorWall: number;
  speed: Speed = 1;
  direction: 1 | -1 = 1;
  playing = false;
  live = false;
  /** Earliest instant the playhead may reach (retention start); `now` is the latest. */
  minMs = -Infinity;
  /** After each change asked for (play, pause, speed, direction, seek, step, live): the
   * page's frame loop wakes (lib/framepace.ts). Not after `hold`, which the frames make. */
  onChange: () => void = () => {};

  constructor(timeMs: number, wallMs: number) {
    this.anchorTime = timeMs;
    this.anchorWall = wallMs;
  }

  /** The playhead at wall instant `wallMs` (which is also "now" on the server's clock). */
  time(wallMs: number): number {
    if (this.live) return wallMs;
    if (!this.playing) return this.clamp(this.anchorTime, wallMs);
    const t = this.anchorTime + this.direction * this.speed * (wallMs - this.anchorWall);
    return this.clamp(t, wallMs);
  }

  private clamp(t: number, wallMs: number): number {
    return Math.min(wallMs, Math.max(this.minMs, t));
  }

  /** Re-anchor at the current playhead so a change of rate does not make time jump. */
  private reanchor(wallMs: number): void {
    this.anchorTime = this.time(wallMs);
    this.anchorWall = wallMs;
  }

  play(wallMs: number): void {
    this.reanchor(wallMs);
    this.live = false;
    this.playing = true;
    this.onChange();
  }

  pause(wallMs: number): void {
    this.reanchor(wallMs);
    this.live = false;
    this.playing = false;
    this.onChange();
  }

  toggle(wallMs: number): void {
    if (this.playing || this.live) this.pause(wallMs);
    else this.play(wallMs);
  }

  setSpeed(speed: Speed, wallMs: number): void {
    this.reanchor(wallMs);
    this.speed = speed;
    this.onChange();
  }

  setDirection(direction: 1 | -1, wallMs: number): void {
    this.reanchor(wallMs);
    this.direction = direction;
    this.onChange();
  }

  seek(timeMs: number, wallMs: number): void {
    // Leaving live for a chosen moment stops there, to look at it.
    if (this.live) this.playing = false;
    this.live = false;
    this.anchorTime = this.clamp(timeMs, wallMs);
    this.anchorWall = wallMs;
    this.onChange();
  }

  /** Holds the playhead where it is while keeping the play state (the buffer is behind). */
  hold(timeMs: number, wallMs: number): void {
    this.anchorTime = this.clamp(timeMs, wallMs);
    this.anchorWall = wallMs;
  }

  step(sign: 1 | -1, wallMs: number): void {
    const t = this.time(wallMs) + sign * stepMs(this.speed);
    this.pause(wallMs);
    this.seek(t, wallMs);
  }

  goLive(wallMs: number): void {
    this.live = true;
    this.playing = true;
    this.direction = 1;
    this.anchorTime = wallMs;
    this.anchorWall = wallMs;
    this.onChange();
  }

  /** True when playing forward has caught up with now (the UI may then switch to live). */
  atNow(wallMs: number): boolean {
    return this.time(wallMs) >= wallMs;
  }

  state(wallMs: number): ClockState {
    return {
      timeMs: this.time(wallMs),
      speed: this.speed,
      direction: this.direction,
      playing: this.playing,
      live: this.live,
    };
  }
}
