import { afterEach, beforeEach, describe, expect, it, vi } from "vitest";
import { LiveConnection } from "../src/lib/live";

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
    const c = new LiveConnection("ws://x/api/v1/live", () => {}, (re) => opened.push(re));
    c.start();
    FakeSocket.all[0].onopen!();
    FakeSocket.all[0].onclose!();
    expect(c.status.connected).toBe(false);
    vi.advanceTimersByTime(999);
    expect(FakeSocket.all).toHaveLength(1);
    vi.advanceTimersByTime(1);
    expect(FakeSocket.all).toHaveLength(2);
    FakeSocket.all[1].onclose!();
    vi.advanceTimersByTime(1999);
    expect(FakeSocket.all).toHaveLength(2);
    vi.advanceTimersByTime(1);
    FakeSocket.all[2].onopen!();
    expect(opened).toEqual([false, true]);
    expect(c.status.reconnects).toBe(2);
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
});
