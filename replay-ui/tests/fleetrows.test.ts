import { afterEach, describe, expect, it, vi } from "vitest";
import { useFleetRows } from "../src/composables/useFleetRows";
import { addToTrack, SPEED_WINDOW_MS } from "../src/lib/fleet";
import type { ReplayEngine } from "../src/lib/engine";
import type { Pose } from "../src/lib/types";

afterEach(() => vi.unstubAllGlobals());

/** A deterministic generator (mulberry32): the same cases on every run. */
function random(seed: number) {
  return () => {
    seed = (seed + 0x6d2b79f5) | 0;
    let t = Math.imul(seed ^ (seed >>> 15), 1 | seed);
    t = (t + Math.imul(t ^ (t >>> 7), 61 | t)) ^ t;
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

const pose = (robotId: string, ts_ms: number, x: number): Pose =>
  ({ robotId, ts_ms, position: [x, 0, 0], orientation: [0, 0, 0, 1], battery_level: 50, charging: false, loaded: false, path: null });

describe("the fleet's speeds while live", () => {
  it("keeps each robot's stream poses of the window, in time order, whatever order they come in (generated)", () => {
    const rnd = random(42);
    for (let run = 0; run < 200; run++) {
      const tracks = new Map<string, Pose[]>();
      const sent: Pose[] = [];
      for (let i = 0; i < 40; i++) sent.push(pose(`r${Math.floor(rnd() * 3)}`, Math.floor(rnd() * 3 * SPEED_WINDOW_MS), i));
      // A stream mostly in order, some late and some repeated.
      sent.sort((a, b) => a.ts_ms - b.ts_ms);
      for (let i = 0; i + 1 < sent.length; i++) if (rnd() < 0.2) [sent[i], sent[i + 1]] = [sent[i + 1], sent[i]];
      for (const p of sent) addToTrack(tracks, p);
      for (const p of sent.slice(0, 5)) addToTrack(tracks, { ...p, position: [-1, 0, 0] }); // repeats
      for (const [id, track] of tracks) {
        const times = track.map((p) => p.ts_ms);
        expect(times).toEqual([...new Set(times)].sort((a, b) => a - b));
        expect(times[times.length - 1] - times[0]).toBeLessThanOrEqual(SPEED_WINDOW_MS);
        // Every pose of the robot within the window of the newest one kept is there.
        const newest = times[times.length - 1];
        const due = new Set(sent.filter((p) => p.robotId === id && p.ts_ms >= newest - SPEED_WINDOW_MS).map((p) => p.ts_ms));
        expect(new Set(times)).toEqual(due);
      }
    }
  });

  it("live, reads no poses for the speeds: the stream's are used; paused, it reads them", async () => {
    const asked: string[] = [];
    vi.stubGlobal("fetch", async (url: string) => {
      asked.push(url);
      return new Response("[]", { status: 200 });
    });
    const now = 1_800_000_000_000;
    const liveTracks = new Map([["r1", [pose("r1", now - 1000, 0), pose("r1", now, 1.5)]]]);
    const engine = {
      playhead: now,
      clock: { live: true },
      liveTracks,
      api: { base: "" },
      robots: () => [{ robotId: "r1", pose: pose("r1", now, 1.5), offline: false }],
    } as unknown as ReplayEngine;
    const rows = useFleetRows(engine, (r) => r);
    for (let tick = 0; tick < 50; tick++) {
      engine.playhead = now + tick * 200; // live: the playhead runs with the clock
      rows.refreshRows();
      await Promise.resolve();
    }
    expect(asked).toEqual([]);
    expect(rows.fleet.value[0].speed).toBeCloseTo(1.5);
    (engine.clock as { live: boolean }).live = false;
    rows.refreshRows();
    expect(asked.filter((u) => u.includes("/api/v1/poses?"))).toHaveLength(1);
  });
});
