import { describe, expect, it } from "vitest";
import { fleetRows, placeLabels, robotColour, speedAt } from "../src/lib/fleet";
import { BatteryScales } from "../src/lib/battery";
import type { Pose } from "../src/lib/types";

function pose(id: string, ts: number, x: number, extra: Partial<Pose> = {}): Pose {
  return { robotId: id, ts_ms: ts, position: [x, 0, 0], orientation: [0, 0, 0, 1], battery_level: 61, charging: false, loaded: true, path: null, ...extra };
}

describe("fleet", () => {
  it("shows battery as a percentage of any 2019 scale", () => {
    // Each robot on its own scale: a fraction robot's 0.5 is 50 %, a percent robot's 4 is 4 %.
    const scales = new BatteryScales();
    const rows = fleetRows([["pct", 61], ["frac", 0.5], ["low", 4], ["none", null]].map(([id, level]) =>
      ({ robotId: id as string, pose: pose(id as string, 0, 0, { battery_level: level as number | null }), offline: false })),
    new Map(), 0, "", scales);
    expect(Object.fromEntries(rows.map((r) => [r.robotId, r.batteryPct]))).toEqual({ pct: 61, frac: 50, low: 4, none: null });
  });

  it("gives each robot one stable colour, different between robots", () => {
    expect(robotColour("sim-001")).toBe(robotColour("sim-001"));
    const colours = new Set(["sim-000", "sim-001", "sim-002", "sim-003", "sim-004"].map(robotColour));
    expect(colours.size).toBe(5);
  });

  it("takes speed from the last two samples before the instant", () => {
    const track = [pose("a", 0, 0), pose("a", 1000, 1.5), pose("a", 2000, 1.5)];
    expect(speedAt(track, 1500)).toBeCloseTo(1.5);
    expect(speedAt(track, 2000)).toBe(0);
    expect(speedAt(track, 500)).toBeNull();
    expect(speedAt([pose("a", 0, 0), pose("a", 60_000, 5)], 60_000)).toBeNull();
  });

  it("lists robots by id, searchable, with goal and flags", () => {
    const robots = [
      { robotId: "sim-002", pose: pose("sim-002", 5, 0, { path: [[1, 2], [3, 4]], charging: "yes" }), offline: false },
      { robotId: "sim-001", pose: pose("sim-001", 7, 0), offline: true },
    ];
    const rows = fleetRows(robots, new Map(), 10, "");
    expect(rows.map((r) => [r.robotId, r.online, r.batteryPct, r.charging, r.loaded, r.goal])).toEqual([
      ["sim-001", false, 61, "no", "yes", null], ["sim-002", true, 61, "yes", "yes", [3, 4]]]);
    expect(fleetRows(robots, new Map(), 10, " 002").map((r) => r.robotId)).toEqual(["sim-002"]);
  });

  it("places labels without overlap, leaving out one that fits nowhere", () => {
    const boxes = placeLabels([{ x: 0, y: 0, w: 60, h: 14 }, { x: 2, y: 0, w: 60, h: 14 }, { x: 4, y: 1, w: 60, h: 14 }, { x: 1, y: 2, w: 60, h: 14 }, { x: 3, y: 3, w: 60, h: 14 }], 8);
    const placed = boxes.filter((b) => b !== null) as { x: number; y: number; w: number; h: number }[];
    for (let i = 0; i < placed.length; i++) for (let j = i + 1; j < placed.length; j++) {
      const [a, b] = [placed[i], placed[j]];
      expect(a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h).toBe(false);
    }
    expect(boxes[0]).not.toBeNull();
    expect(boxes[4]).toBeNull();
  });
});

describe("robot colours", () => {
  it("sets similar ids apart", () => {
    const ids = ["robot-0000", "robot-0001", "robot-0002"];
    expect(new Set(ids.map(robotColour)).size).toBe(3);
  });
});
