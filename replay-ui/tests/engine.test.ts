import { afterEach, beforeEach, describe, expect, it, vi } from "vitest";
import type { MapAt } from "../src/lib/api";
import type { Speed } from "../src/lib/clock";
import { FRAME_WAIT_MAX_MS, ReplayEngine, SEEK_RETRY_MS, SETTLE_MS } from "../src/lib/engine";
import { ApiError } from "../src/lib/request";
import type { EventWindow, RobotAt } from "../src/lib/types";

const NOW = Date.UTC(2026, 10, 21, 12, 0, 0);
const T = NOW - 3_600_000;
const hex = (i: number) => i.toString(16).padStart(32, "0");
const settle = () => new Promise((r) => setTimeout(r, 0));

function deferred<V>() {
  let resolve!: (v: V) => void;
  const promise = new Promise<V>((r) => (resolve = r));
  return { promise, resolve };
}

const MAP: MapAt = {
  at_ms: T,
  meta: null,
  chunks: [0, 1, 2].map((i) => ({ row: 0, column: i, ts_ms: T - 1000, robotId: "r1", content_hash: hex(i + 1) })),
};
const ROBOTS: RobotAt[] = [];
const EMPTY: EventWindow = { from_ms: 0, to_ms: 0, step_ms: 0, chunks: [], poses: [], truncated: false };

/** An engine over stubbed API calls, with its wall and performance clocks in the test's hand. */
function makeEngine() {
  const engine = new ReplayEngine("", NOW);
  let perf = 1000;
  engine.now = () => NOW;
  engine.perfNow = () => perf;
  const map = deferred<MapAt>();
  const robots = deferred<RobotAt[]>();
  const calls = {
    map: vi.spyOn(engine.api, "map").mockImplementation(() => map.promise),
    robots: vi.spyOn(engine.api, "robotsAt").mockImplementation(() => robots.promise),
    events: vi.spyOn(engine.api, "events").mockResolvedValue(EMPTY),
    pictures: vi.spyOn(engine.images, "requestMany").mockImplementation(() => {}),
  };
  return { engine, map, robots, calls, advance: (ms: number) => (perf += ms) };
}

/** An engine seeked to T (at `speed`, if given, before the seek) with the map and `robots`
 * answered and a 1 x 3 chunk grid known. */
async function seekedEngine(opts: { speed?: Speed; robots?: RobotAt[] } = {}) {
  const e = makeEngine();
  if (opts.speed !== undefined) e.engine.clock.setSpeed(opts.speed, NOW);
  const done = e.engine.seek(T);
  e.map.resolve(MAP);
  e.robots.resolve(opts.robots ?? ROBOTS);
  await done;
  e.engine.meta = { CHUNK_ROWS: 1, CHUNK_COLS: 3, CHUNK_WIDTH: 100, CHUNK_HEIGHT: 100 } as never;
  return e;
}

beforeEach(() => {
  vi.stubGlobal("location", { protocol: "http:", host: "127.0.0.1:8080" });
});
afterEach(() => {
  vi.restoreAllMocks();
  vi.unstubAllGlobals();
});

describe("seek", () => {
  it("asks for the map and the robots at T at once, and for the pictures as soon as the map is here", async () => {
    const { engine, map, robots, calls } = makeEngine();
    const done = engine.seek(T);
    expect(calls.map).toHaveBeenCalledWith(T, expect.any(AbortSignal));
    expect(calls.robots).toHaveBeenCalledWith(T, expect.any(AbortSignal)); // before the map answered
    map.resolve(MAP);
    await settle();
    // The robots are still on the way; the pictures are asked for already.
    expect(calls.pictures).toHaveBeenCalledWith(MAP.chunks.map((c) => c.content_hash));
    expect(engine.seeking).toBe(true);
    robots.resolve(ROBOTS);
    await done;
    expect(engine.seeking).toBe(false);
    expect(engine.seekPendingFrame).toBe(true);
    expect(engine.state.cells.size).toBe(3);
  });

  it("does not ask for the pictures of a seek already overtaken by another", async () => {
    const { engine, map, robots, calls } = makeEngine();
    const first = engine.seek(T);
    calls.map.mockImplementation(() => new Promise(() => {}));
    void engine.seek(T + 60_000);
    map.resolve(MAP);
    robots.resolve(ROBOTS);
    await first;
    expect(calls.pictures).not.toHaveBeenCalled();
  });

  it("records the seek time once, at its first complete frame", async () => {
    const { engine, map, robots, advance } = makeEngine();
    const done = engine.seek(T);
    map.resolve(MAP);
    robots.resolve(ROBOTS);
    await done;
    advance(120);
    engine.seekFrameDrawn();
    engine.seekFrameDrawn();
    expect(engine.seekTimes).toEqual([120]);
  });
});

describe("look-ahead after a seek", () => {
  it("paused: waits for the seek's first frame, then for the playhead to settle", async () => {
    const { engine, calls, advance } = await seekedEngine();
    engine.frame();
    expect(calls.events).not.toHaveBeenCalled(); // the frame is not drawn yet
    engine.seekFrameDrawn();
    engine.frame();
    expect(calls.events).not.toHaveBeenCalled(); // a scrub may seek again right away
    expect(engine.settled()).toBe(false);
    advance(SETTLE_MS);
    expect(engine.settled()).toBe(true);
    engine.frame();
    expect(calls.events).toHaveBeenCalledTimes(1);
  });

  it("playing: fetched as soon as the seek's first frame is drawn", async () => {
    const { engine, calls } = await seekedEngine();
    engine.clock.play(NOW);
    engine.frame();
    expect(calls.events).not.toHaveBeenCalled();
    engine.seekFrameDrawn();
    engine.frame();
    expect(calls.events).toHaveBeenCalledTimes(1);
  });

  it("a frame that never completes holds the look-ahead back only for a while", async () => {
    const { engine, calls, advance } = await seekedEngine();
    engine.clock.play(NOW);
    advance(FRAME_WAIT_MAX_MS - 1);
    engine.frame();
    expect(calls.events).not.toHaveBeenCalled();
    advance(1);
    engine.frame();
    expect(calls.events).toHaveBeenCalledTimes(1);
  });
});

describe("pausing above 60x", () => {
  it("replaces the compacted map with the exact one at the resting playhead, once", async () => {
    const { engine, calls, advance } = await seekedEngine({ speed: 3600 });
    engine.seekFrameDrawn();
    expect(engine.buffer.chunkStepMs).toBe(60_000);
    // Compacted writes moved the map past the seek: only bucket boundaries are exact now.
    engine.buffer.chunks = [{ row: 0, column: 0, ts_ms: T + 30_000, robotId: "r2", content_hash: hex(9) }];
    engine.buffer.to = T + 120_000;
    engine.clock.hold(T + 40_000, NOW);
    advance(SETTLE_MS);
    engine.frame();
    expect(calls.map).toHaveBeenLastCalledWith(T + 40_000, expect.any(AbortSignal));
    expect(engine.exactMapLoads).toBe(1);
    await settle();
    expect(engine.mapExactAt).toBe(T + 40_000);
    engine.seekFrameDrawn();
    expect(engine.seekTimes).toHaveLength(1); // the user's seek only, not the one in place
    advance(SETTLE_MS);
    engine.frame();
    expect(engine.exactMapLoads).toBe(1);
  });
});

describe("a seek and a busy server", () => {
  it("cancels the reads of a seek that a newer one superseded", async () => {
    const { engine, calls } = makeEngine();
    void engine.seek(T);
    const first = calls.map.mock.calls[0][1];
    const firstRobots = calls.robots.mock.calls[0][1];
    expect(first?.aborted).toBe(false);
    void engine.seek(T + 60_000);
    expect(first?.aborted).toBe(true);
    expect(firstRobots?.aborted).toBe(true);
    expect(calls.map.mock.calls[1][1]?.aborted).toBe(false);
  });

  it("keeps the link's instant while it loads and after it failed, and tries again by itself", async () => {
    const { engine, calls, map, robots } = makeEngine();
    let wall = NOW;
    engine.now = () => wall;
    calls.map.mockRejectedValueOnce(new ApiError(503, "The server stayed too busy to load the map."));
    const done = engine.seek(T);
    expect(engine.playhead).toBe(T); // at once: the address names the link's instant
    await done;
    expect(engine.error).toContain("too busy");
    expect(engine.playhead).toBe(T);
    for (let i = 0; i < 5; i++) {
      wall += (SEEK_RETRY_MS - 1) / 5;
      engine.frame();
    }
    expect(calls.map).toHaveBeenCalledTimes(1); // not every frame
    wall += 1;
    engine.frame();
    expect(calls.map).toHaveBeenCalledTimes(2);
    expect(calls.map).toHaveBeenLastCalledWith(T, expect.any(AbortSignal));
    map.resolve(MAP);
    robots.resolve(ROBOTS);
    await settle();
    await settle();
    expect(engine.error).toBeNull();
    expect(engine.state.cells.size).toBe(3);
    expect(engine.playhead).toBe(T);
  });
});

describe("pausing above 60x, the server failing", () => {
  it("does not ask again every frame for the exact map at the same playhead", async () => {
    const { engine, calls, advance } = await seekedEngine({ speed: 3600 });
    engine.seekFrameDrawn();
    engine.buffer.to = T + 120_000;
    engine.clock.hold(T + 40_000, NOW);
    calls.map.mockRejectedValue(new Error("503"));
    advance(SETTLE_MS);
    engine.frame();
    await settle();
    expect(engine.error).toContain("503");
    for (let i = 0; i < 5; i++) engine.frame();
    expect(calls.map).toHaveBeenCalledTimes(2); // the seek, then one seek in place
  });
});

describe("robots at the playhead", () => {
  const pose = (id: string, ts: number, x = 1): RobotAt => ({
    robotId: id, ts_ms: ts, position: [x, 2, 0], orientation: [0, 0, 0, 1], battery_level: 50,
    charging: false, loaded: false, path: null,
  });

  async function seekedWith(robots: RobotAt[]) {
    const e = await seekedEngine({ robots });
    e.engine.seekFrameDrawn();
    return e;
  }

  it("playing at 3600x, a robot sampled once a minute is online, one silent past the step is not", async () => {
    const { engine } = await seekedWith([]);
    engine.setSpeed(3600);
    engine.buffer.stepMs = 60_000;
    engine.clock.play(NOW);
    engine.playhead = T;
    engine.buffer.tracks.set("busy", [pose("busy", T - 50_000)]);
    engine.buffer.tracks.set("gone", [pose("gone", T - 60_000 - 10_001)]);
    const byId = new Map(engine.robots().map((r) => [r.robotId, r]));
    expect(byId.get("busy")!.offline).toBe(false);
    expect(byId.get("gone")!.offline).toBe(true);
  });

  it("after a seek, the robots are the history's robots at T, online as the server says", async () => {
    const { engine } = await seekedWith([{ ...pose("a", T - 2000), online: true }, { ...pose("b", T - 40_000), online: false }]);
    const byId = new Map(engine.robots().map((r) => [r.robotId, r]));
    expect([byId.get("a")!.offline, byId.get("b")!.offline]).toEqual([false, true]);
  });

  it("pausing elsewhere loads the exact robots at the new playhead and shows them instead of samples", async () => {
    const { engine, calls, advance } = await seekedWith([]);
    const exact = deferred<RobotAt[]>();
    calls.robots.mockImplementation(() => exact.promise);
    engine.buffer.tracks.set("r1", [pose("r1", T + 60_000 - 45_000, 9)]); // a sample 45 s old
    engine.buffer.from = T;
    engine.buffer.to = T + 120_000;
    engine.playhead = T + 60_000;
    engine.clock.hold(T + 60_000, NOW);
    advance(SETTLE_MS);
    engine.frame();
    expect(calls.robots).toHaveBeenLastCalledWith(T + 60_000);
    exact.resolve([{ ...pose("r1", T + 60_000 - 1000, 3), online: true }]);
    await settle();
    const [r1] = engine.robots();
    expect([r1.x, r1.pose.ts_ms, r1.offline]).toEqual([3, T + 60_000 - 1000, false]);
    engine.frame();
    expect(calls.robots).toHaveBeenCalledTimes(2); // once by the seek, once on pausing: not every frame
  });
});

describe("waking the page's frame loop", () => {
  it("wakes it for a clock action, a seek's end, a live pose or map write, the exact robots at rest", async () => {
    const e = makeEngine();
    let wakes = 0;
    e.engine.onWake = () => wakes++;
    const woke = async (what: string, act: () => unknown) => {
      const before = wakes;
      await act();
      await settle();
      expect(wakes, what).toBeGreaterThan(before);
    };
    const done = e.engine.seek(T);
    await woke("the seek's end", async () => {
      e.map.resolve(MAP);
      e.robots.resolve(ROBOTS);
      await done;
    });
    await woke("play", () => e.engine.clock.play(NOW));
    await woke("pause", () => e.engine.clock.pause(NOW));
    await woke("a speed", () => e.engine.setSpeed(8));
    const onLive = (m: unknown) => (e.engine as unknown as { onLive: (m: unknown) => void }).onLive(m);
    e.engine.clock.goLive(NOW);
    await woke("a live pose", () => onLive({ type: "pose", robotId: "r9", ts_ms: NOW, position: [1, 2, 0] }));
    await woke("a live map write", () => onLive({ type: "chunk", row: 0, column: 1, ts_ms: NOW, robotId: "r9", content_hash: hex(9) }));
  });

  it("wakes it when a seek fails: the error is shown without waiting for the idle tick", async () => {
    const e = makeEngine();
    let wakes = 0;
    e.engine.onWake = () => wakes++;
    e.calls.robots.mockRejectedValueOnce(new ApiError(400, "refused"));
    const done = e.engine.seek(T);
    const before = wakes;
    e.map.resolve(MAP);
    await done;
    expect(e.engine.error).not.toBeNull();
    expect(wakes).toBeGreaterThan(before);
  });
});

