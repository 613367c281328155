import { afterEach, describe, expect, it, vi } from "vitest";
import { Api, downsample, fetchRetrying, mapFromWire } from "../src/lib/api";
import type { Pose } from "../src/lib/types";

function pose(robotId: string, ts: number): Pose {
  return { robotId, ts_ms: ts, position: [0, 0, 0], orientation: [0, 0, 0, 1], battery_level: 1, charging: false, loaded: false, path: null };
}

function respond(routes: Record<string, unknown>) {
  const calls: string[] = [];
  vi.stubGlobal("fetch", async (url: string) => {
    calls.push(url);
    const path = url.split("?")[0];
    if (!(path in routes)) return new Response(JSON.stringify({ detail: "Not Found" }), { status: 404, statusText: "Not Found" });
    return new Response(JSON.stringify(routes[path]), { status: 200 });
  });
  return calls;
}

afterEach(() => vi.unstubAllGlobals());

describe("Api", () => {
  it("falls back to chunk-events and poses while /events is missing, and remembers it", async () => {
    const chunk = { row: 1, column: 2, ts_ms: 5, robotId: "r", content_hash: "a".repeat(32) };
    const calls = respond({ "/api/v1/chunk-events": [chunk], "/api/v1/poses": [pose("r", 1), pose("r", 2), pose("r", 70_000)] });
    const api = new Api();
    const w = await api.events(0, 100_000, 60_000);
    expect(w.chunks).toEqual([chunk]);
    expect(w.poses.map((p) => p.ts_ms)).toEqual([1, 70_000]);
    expect(w.truncated).toBe(false);
    await api.events(0, 100_000, 0);
    expect(calls.filter((c) => c.startsWith("/api/v1/events"))).toHaveLength(1);
  });

  it("asks for the map at T in the compact layout and reads either layout", async () => {
    const chunk = { row: 1, column: 2, ts_ms: 5, robotId: "r", content_hash: "a".repeat(32) };
    const calls = respond({ "/api/v1/map": {
      at_ms: 9, meta: null, fields: ["row", "column", "ts_ms", "robotId", "content_hash"], cells: [[1, 2, 5, "r", "a".repeat(32)]],
    } });
    expect(await new Api().map(9)).toEqual({ at_ms: 9, meta: null, chunks: [chunk] });
    expect(calls).toEqual(["/api/v1/map?at=9&layout=compact"]);
    // An older server ignores the layout and answers with one object per chunk.
    respond({ "/api/v1/map": { at_ms: 9, meta: null, chunks: [{ ...chunk, timestamp: "1970-01-01T00:00:00.005" }] } });
    expect((await new Api().map(9)).chunks[0]).toMatchObject(chunk);
    // Fields in another order are read by name.
    expect(mapFromWire({ at_ms: 9, meta: null, fields: ["content_hash", "robotId", "ts_ms", "column", "row"], cells: [["a".repeat(32), "r", 5, 2, 1]] }).chunks).toEqual([chunk]);
  });

  it("uses /events when it is there", async () => {
    const body = { from_ms: 0, to_ms: 10, step_ms: 0, chunks: [], poses: [], truncated: false };
    respond({ "/api/v1/events": body });
    expect(await new Api().events(0, 10, 0)).toEqual(body);
  });

  it("treats a missing timeline or conflicts endpoint as no data, not an error", async () => {
    respond({});
    const api = new Api();
    expect(await api.timeline(0, 10, 5)).toBeNull();
    expect(await api.conflicts(0, 10)).toEqual([]);
  });
});

describe("downsample", () => {
  it("keeps each robot's first pose per step", () => {
    const got = downsample([pose("a", 0), pose("b", 10), pose("a", 500), pose("a", 1000), pose("b", 1999)], 1000);
    expect(got.map((p) => `${p.robotId}${p.ts_ms}`)).toEqual(["a0", "b10", "a1000", "b1999"]);
  });
});

describe("fetchRetrying", () => {
  it("retries a 503 or 429 after its Retry-After, then returns the answer", async () => {
    const answers = [
      new Response(JSON.stringify({ detail: "busy" }), { status: 503, headers: { "Retry-After": "2" } }),
      new Response(JSON.stringify({ detail: "slow down" }), { status: 429, headers: { "Retry-After": "60" } }),
      new Response(JSON.stringify({ ok: 1 }), { status: 200 }),
    ];
    vi.stubGlobal("fetch", async () => answers.shift());
    const waits: number[] = [];
    const r = await fetchRetrying("/api/v1/robots", async (ms) => { waits.push(ms); });
    expect(r.status).toBe(200);
    expect(waits).toEqual([2000, 5000]); // Retry-After, capped at 5 s
  });

  it("gives up after three retries with the last refusal", async () => {
    vi.stubGlobal("fetch", async () => new Response("{}", { status: 503 }));
    const waits: number[] = [];
    const r = await fetchRetrying("/x", async (ms) => { waits.push(ms); });
    expect(r.status).toBe(503);
    expect(waits).toEqual([1000, 1000, 1000]);
  });
});
