/**
 * Where each robot is at an instant: interpolated between samples at low speed (smooth
 * motion), the latest sample at or before T at high speed (no invented positions between
 * downsampled samples minutes apart).
 */
import { upperBound } from "./mapstate";
import type { Pose } from "./types";
import { levelPercent, type BatteryScale } from "./battery";

/** Above this speed poses are sampled, not interpolated. */
export const INTERPOLATE_MAX_SPEED = 8;
/** Samples further apart than this are not interpolated (the robot was silent). */
export const MAX_GAP_MS = 5_000;

export function lerpAngle(a: number, b: number, f: number): number {
  let d = b - a;
  while (d > Math.PI) d -= 2 * Math.PI;
  while (d < -Math.PI) d += 2 * Math.PI;
  return a + d * f;
}

/** Index of the latest sample with ts <= t, or -1. */
export function latestIndex(track: Pose[], t: number): number {
  return upperBound(track, t) - 1;
}

export interface PlacedPose {
  pose: Pose; // the sample the status (battery, path...) comes from
  x: number;
  y: number;
  yaw: number | null; // null: take it from the pose's quaternion
}

export function poseAt(track: Pose[], t: number, interpolate: boolean): PlacedPose | null {
  const i = latestIndex(track, t);
  if (i < 0) return null;
  const a = track[i];
  const placed: PlacedPose = { pose: a, x: a.position[0], y: a.position[1], yaw: null };
  if (!interpolate || i + 1 >= track.length) return placed;
  const b = track[i + 1];
  const gap = b.ts_ms - a.ts_ms;
  if (gap <= 0 || gap > MAX_GAP_MS) return placed;
  const f = (t - a.ts_ms) / gap;
  placed.x = a.position[0] + (b.position[0] - a.position[0]) * f;
  placed.y = a.position[1] + (b.position[1] - a.position[1]) * f;
  placed.yaw = lerpAngle(yawOfPose(a), yawOfPose(b), f);
  return placed;
}

export function yawOfPose(p: Pose): number {
  const [x, y, z, w] = p.orientation;
  return Math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z));
}

/** A battery level on the robot's `scale` (lib/battery.ts) as a colour. */
export function batteryColour(level: number | null | undefined, scale: BatteryScale = "percent"): string {
  const pct = levelPercent(level, scale);
  if (pct === null) return "#888888";
  if (pct < 20) return "#d62728";
  if (pct < 50) return "#ff9f1c";
  return "#2ca02c";
}

/** The server's defaults (settings clock_skew_threshold_s, robot_offline_after_s). */
export const CLOCK_SKEW_THRESHOLD_MS = 5_000;
export const OFFLINE_AFTER_MS = 10_000;

export interface RobotStatus {
  online: boolean;
  skewMs: number | null;
  skewFlag: boolean;
}

/**
 * Online and clock skew of the pose shown at T: the server's verdict when it describes
 * that very pose (robots-at), else worked out from the pose's receive time the same way.
 */
export function robotStatus(
  pose: Pose,
  info: { ts_ms: number; clock_skew_ms?: number; clock_skew_flag?: boolean } | undefined,
  t: number,
): RobotStatus {
  const same = info !== undefined && info.ts_ms === pose.ts_ms && info.clock_skew_ms !== undefined;
  const skewMs = same ? info!.clock_skew_ms! : pose.receive_time_ms !== undefined ? pose.receive_time_ms - pose.ts_ms : null;
  const skewFlag = same && info!.clock_skew_flag !== undefined ? info!.clock_skew_flag : skewMs !== null && Math.abs(skewMs) > CLOCK_SKEW_THRESHOLD_MS;
  return { online: t - pose.ts_ms <= OFFLINE_AFTER_MS, skewMs, skewFlag };
}
