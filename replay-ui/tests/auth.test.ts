import { afterEach, describe, expect, it } from "vitest";
import { apiToken, authHeaders, liveProtocols, setApiToken } from "../src/lib/auth";

class MemoryStorage {
  items = new Map<string, string>();
  getItem(k: string) { return this.items.get(k) ?? null; }
  setItem(k: string, v: string) { this.items.set(k, v); }
  removeItem(k: string) { this.items.delete(k); }
}

describe("the browser's API token", () => {
  afterEach(() => {
    delete (globalThis as { localStorage?: unknown }).localStorage;
  });

  it("sends nothing without a token", () => {
    (globalThis as { localStorage?: unknown }).localStorage = new MemoryStorage();
    expect(apiToken()).toBe("");
    expect(authHeaders()).toEqual({});
    expect(liveProtocols()).toBeUndefined();
  });

  it("sends a stored token as a bearer header and as the live subprotocol", () => {
    (globalThis as { localStorage?: unknown }).localStorage = new MemoryStorage();
    setApiToken("  robot-token \n");
    expect(authHeaders()).toEqual({ Authorization: "Bearer robot-token" });
    expect(liveProtocols()).toEqual(["mapservice.live", "bearer.robot-token"]);
    setApiToken("");
    expect(authHeaders()).toEqual({});
  });

  it("works without storage (a page with storage disabled)", () => {
    expect(apiToken()).toBe("");
    setApiToken("x");
    expect(authHeaders()).toEqual({});
  });
});
