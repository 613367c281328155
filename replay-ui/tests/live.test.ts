import { afterEach, beforeEach, describe, expect, it, vi } from "vitest";
import { BACKOFF_CAP_MS, LiveConnection, STABLE_MS, backoffDelay, liveUrl } from "../src/lib/live";

class FakeSocket {
  static all: FakeSocket[] = [];
  onopen: (() => void) | null = null;
  onmessage: ((e: { data: string }) => void) | null = null;
  onclose: (() => void) | null = null;
  constructor(public url: string) {
    FakeSocket.all.push(this);
  }
  close() {
    this.onclose?.();
  }
}

describe("LiveConnection", () => {
  beforeEach(() => {
    FakeSocket.all = [];
    vi.useFakeTimers();
    vi.stubGlobal("WebSocket", FakeSocket);
  });
  afterEach(() => {
    vi.useRealTimers();
    vi.unstubAllGlobals();
  });

  it("reconnects with a growing backoff and tells the page it reconnected", () => {
    const opened: boolean[] = [];
    // random() = 0.5: each wait is 3/4 of its ceiling (1 s, 2 s, ...).
    const c = new LiveConnection("ws://x/api/v1/live", () => {}, (re) => opened.push(re), () => 0.5);
    c.start();
    FakeSocket.all[0].onopen!();
    FakeSocket.all[0].onclose!();
    expect(c.status.connected).toBe(false);
    vi.advanceTimersByTime(749);
    expect(FakeSocket.all).toHaveLength(1);
    vi.advanceTimersByTime(1);
    expect(FakeSocket.all).toHaveLength(2);
    FakeSocket.all[1].onclose!();
    vi.advanceTimersByTime(1499);
    expect(FakeSocket.all).toHaveLength(2);
    vi.advanceTimersByTime(1);
    FakeSocket.all[2].onopen!();
    expect(opened).toEqual([false, true]);
    expect(c.status.reconnects).toBe(2);
  });

  it("backs off exponentially with jitter in the upper half, capped at 30 s", () => {
    const low = Array.from({ length: 8 }, (_, n) => backoffDelay(n, () => 0));
    const high = Array.from({ length: 8 }, (_, n) => backoffDelay(n, () => 0.999999));
    expect(low).toEqual([500, 1000, 2000, 4000, 8000, 15_000, 15_000, 15_000]);
    expect(high).toEqual([1000, 2000, 4000, 8000, 16_000, 30_000, 30_000, 30_000]);
    expect(backoffDelay(1000, () => 0.999999)).toBe(BACKOFF_CAP_MS);
    const spread = new Set(Array.from({ length: 50 }, () => backoffDelay(3)));
    expect(spread.size).toBeGreaterThan(10); // tabs that lost the server together spread out
  });

  it("does not reset the backoff when the server accepts and closes at once (no re-seek storm)", () => {
    const opened: boolean[] = [];
    const c = new LiveConnection("ws://x/api/v1/live", () => {}, (re) => opened.push(re), () => 0.999999);
    c.start();
    // A server whose live feed is not there: every socket opens, then closes (1013/1011).
    for (let t = 0; t < 120_000; t += 100) {
      const ws = FakeSocket.all[FakeSocket.all.length - 1];
      if (ws.onopen && !(ws as unknown as { seen?: boolean }).seen) {
        (ws as unknown as { seen?: boolean }).seen = true;
        ws.onopen();
        ws.onclose!();
      }
      vi.advanceTimersByTime(100);
    }
    // 1 + 2 + 4 + 8 + 16 + 30 + 30 + 30 s: 8 reconnects in two minutes, not 120.
    expect(FakeSocket.all.length).toBeLessThanOrEqual(9);
    expect(opened.filter((re) => re).length).toBeLessThanOrEqual(8);
  });

  it("resets the backoff once a connection proved itself (a message or STABLE_MS open)", () => {
    const c = new LiveConnection("ws://x", () => {}, () => {}, () => 0.999999);
    c.start();
    for (let i = 0; i < 4; i++) {
      FakeSocket.all[i].onclose!();
      vi.advanceTimersByTime(BACKOFF_CAP_MS);
    }
    const n = FakeSocket.all.length;
    FakeSocket.all[n - 1].onopen!();
    FakeSocket.all[n - 1].onmessage!({ data: JSON.stringify({ type: "pose", ts_ms: 1, robotId: "r" }) });
    FakeSocket.all[n - 1].onclose!();
    vi.advanceTimersByTime(1000);
    expect(FakeSocket.all).toHaveLength(n + 1); // back to the first, 1 s wait
    for (let i = 0; i < 3; i++) {
      FakeSocket.all[FakeSocket.all.length - 1].onclose!();
      vi.advanceTimersByTime(BACKOFF_CAP_MS);
    }
    const m = FakeSocket.all.length;
    FakeSocket.all[m - 1].onopen!();
    vi.advanceTimersByTime(STABLE_MS);
    FakeSocket.all[m - 1].onclose!();
    vi.advanceTimersByTime(1000);
    expect(FakeSocket.all).toHaveLength(m + 1);
  });

  it("measures latency from the event time and stops for good when stopped", () => {
    const got: unknown[] = [];
    const c = new LiveConnection("ws://x", (m) => got.push(m), () => {});
    c.start();
    vi.setSystemTime(10_000);
    FakeSocket.all[0].onmessage!({ data: JSON.stringify({ type: "pose", ts_ms: 9_700, robotId: "r" }) });
    expect(c.status.latencyMs).toBe(300);
    expect(got).toHaveLength(1);
    c.stop();
    vi.advanceTimersByTime(60_000);
    expect(FakeSocket.all).toHaveLength(1);
  });

  it("hands on each event of a batched frame in order, counts each, takes latency from the last", () => {
    const got: { ts_ms: number }[] = [];
    const c = new LiveConnection("ws://x", (m) => got.push(m), () => {});
    c.start();
    vi.setSystemTime(10_000);
    const frame = [9_000, 9_500, 9_900].map((ts_ms) => ({ type: "pose", ts_ms, robotId: "r", sent_ms: 9_950 }));
    FakeSocket.all[0].onmessage!({ data: JSON.stringify(frame) });
    expect(got.map((m) => m.ts_ms)).toEqual([9_000, 9_500, 9_900]);
    expect(c.status.messages).toBe(3);
    expect(c.status.latencyMs).toBe(100);
    // A server from before batching sends one object per message.
    FakeSocket.all[0].onmessage!({ data: JSON.stringify({ type: "chunk", ts_ms: 9_950, robotId: "r" }) });
    expect(got).toHaveLength(4);
    expect(c.status.messages).toBe(4);
  });

  it("hands on incident announcements but takes no latency from them (their time is when they were found)", () => {
    const got: { type: string }[] = [];
    const c = new LiveConnection("ws://x", (m) => got.push(m), () => {});
    c.start();
    vi.setSystemTime(10_000);
    const incident = { type: "incident", ts_ms: 9_999, retracted: false, incident: { id: "i" } };
    FakeSocket.all[0].onmessage!({ data: JSON.stringify([{ type: "pose", ts_ms: 9_000, robotId: "r" }, incident]) });
    expect(got.map((m) => m.type)).toEqual(["pose", "incident"]);
    expect(c.status.latencyMs).toBe(1000);
    FakeSocket.all[0].onmessage!({ data: JSON.stringify([incident]) });
    expect(got).toHaveLength(3);
    expect(c.status.latencyMs).toBe(1000);
  });

  it("asks the page's own server for batched frames", () => {
    expect(liveUrl({ protocol: "https:", host: "maps.example:8443" })).toBe("wss://maps.example:8443/api/v1/live?batch=true");
    expect(liveUrl({ protocol: "http:", host: "localhost:8000" })).toBe("ws://localhost:8000/api/v1/live?batch=true");
  });
});
