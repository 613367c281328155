import { afterEach, describe, expect, it, vi } from "vitest";
import { Api, mapFromWire } from "../src/lib/api";

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
  it("asks for the map at T in the compact layout and reads its fields by name", async () => {
    const chunk = { row: 1, column: 2, ts_ms: 5, robotId: "r", content_hash: "a".repeat(32) };
    const calls = respond({ "/api/v1/map": {
      at_ms: 9, meta: null, fields: ["row", "column", "ts_ms", "robotId", "content_hash"], cells: [[1, 2, 5, "r", "a".repeat(32)]],
    } });
    expect(await new Api().map(9)).toEqual({ at_ms: 9, meta: null, chunks: [chunk] });
    expect(calls).toEqual(["/api/v1/map?at=9&layout=compact"]);
    // Fields in another order are read by name.
    expect(mapFromWire({ at_ms: 9, meta: null, fields: ["content_hash", "robotId", "ts_ms", "column", "row"], cells: [["a".repeat(32), "r", 5, 2, 1]] }).chunks).toEqual([chunk]);
  });

  it("uses /events when it is there", async () => {
    const body = { from_ms: 0, to_ms: 10, step_ms: 0, chunks: [], poses: [], truncated: false };
    respond({ "/api/v1/events": body });
    expect(await new Api().events(0, 10, 0)).toEqual(body);
  });

  it("reports a missing endpoint as an error and asks no other endpoint", async () => {
    // The page is served by the API it reads: a 404 is a fault to show, not an older server.
    const calls = respond({});
    const api = new Api();
    for (const read of [
      () => api.events(0, 10, 0),
      () => api.timeline(0, 10, 5),
      () => api.conflicts(0, 10),
      () => api.track("r", 0, 10, 1),
    ]) await expect(read()).rejects.toMatchObject({ status: 404 });
    expect(calls.map((c) => c.split("?")[0])).toEqual([
      "/api/v1/events", "/api/v1/timeline", "/api/v1/conflicts", "/api/v1/robots/r/track",
    ]);
  });

  it("reads the conflicts out of the conflicts answer", async () => {
    const conflict = { ts_ms: 5, row: 1, column: 2, robot_a: "a", robot_b: "b" };
    respond({ "/api/v1/conflicts": { from_ms: 0, to_ms: 10, window_s: 1, rule: "r", conflicts: [conflict], truncated: false } });
    expect(await new Api().conflicts(0, 10)).toEqual([conflict]);
  });
});
