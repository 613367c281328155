import { describe, expect, it } from "vitest";
import { batteryColour, poseAt, robotStatus } from "../src/lib/poses";
import type { Pose } from "../src/lib/types";

function p(ts: number, x: number, y: number, yaw = 0): Pose {
  return {
    robotId: "r", ts_ms: ts, position: [x, y, 0], orientation: [0, 0, Math.sin(yaw / 2), Math.cos(yaw / 2)],
    battery_level: 50, charging: false, loaded: false, path: null,
  };
}

describe("poseAt", () => {
  const track = [p(1000, 0, 0), p(2000, 10, 0, Math.PI / 2), p(10_000, 20, 0)];

  it("interpolates position and heading between close samples at low speed", () => {
    const at = poseAt(track, 1500, true)!;
    expect(at.x).toBeCloseTo(5);
    expect(at.yaw!).toBeCloseTo(Math.PI / 4);
  });

  it("samples the latest pose at or before T at high speed", () => {
    const at = poseAt(track, 1500, false)!;
    expect(at.x).toBe(0);
    expect(at.pose.ts_ms).toBe(1000);
  });

  it("holds the last pose across a silence instead of inventing motion", () => {
    expect(poseAt(track, 5000, true)!.x).toBe(10);
  });

  it("knows nothing before the first sample", () => {
    expect(poseAt(track, 999, true)).toBeNull();
  });

  it("colours battery levels", () => {
    expect(batteryColour(90)).toBe("#2ca02c");
    expect(batteryColour(10)).toBe("#d62728");
    expect(batteryColour(null)).toBe("#888888");
  });
});

describe("robotStatus", () => {
  const pose = { ...p(10_000, 0, 0), receive_time_ms: 17_000 };

  it("flags a skew beyond the threshold worked out from the pose", () => {
    expect(robotStatus(pose, undefined, 12_000)).toEqual({ online: true, skewMs: 7000, skewFlag: true });
  });

  it("takes the server's verdict for the same pose and goes offline after a silence", () => {
    const info = { ts_ms: 10_000, clock_skew_ms: 100, clock_skew_flag: false };
    expect(robotStatus(pose, info, 30_000)).toEqual({ online: false, skewMs: 100, skewFlag: false });
  });
});
