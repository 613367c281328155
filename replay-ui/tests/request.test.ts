import { afterEach, describe, expect, it, vi } from "vitest";
import {
  ApiError, BUSY, explainFailure, fetchRetrying, PATIENCE_MS, RETRY_CAP_MS, retryDelayMs, SESSION_HEADER, SESSION_ID,
  sharedGet, sharedInFlight,
} from "../src/lib/request";
import { getJson } from "../src/lib/api";

afterEach(() => vi.unstubAllGlobals());

/** A seeded generator, so that a failing case can be run again. */
function rng(seed: number): () => number {
  let s = seed >>> 0;
  return () => {
    s = (s * 1664525 + 1013904223) >>> 0;
    return s / 2 ** 32;
  };
}

/** A clock the fake sleeps advance. */
function fakeTime() {
  const clock = { now: 0, waits: [] as number[] };
  const sleep = async (ms: number, signal?: AbortSignal) => {
    if (signal?.aborted) throw signal.reason;
    clock.waits.push(ms);
    clock.now += ms;
  };
  return { clock, sleep, now: () => clock.now };
}

const busy = (status: number, retryAfter?: string) =>
  new Response(JSON.stringify({ detail: "MAPSERVICE_API_CALLER_QUEUE over its share" }), {
    status, headers: retryAfter === undefined ? {} : { "Retry-After": retryAfter },
  });

describe("retryDelayMs", () => {
  it("honours Retry-After (seconds or a date), else backs off growing with jitter, never past the cap", () => {
    const random = rng(7);
    for (let i = 0; i < 2000; i++) {
      const failures = Math.floor(random() * 12);
      const r = random();
      const kind = Math.floor(random() * 4);
      const seconds = Math.floor(random() * 90);
      const now = 1_800_000_000_000;
      const header = kind === 0 ? null : kind === 1 ? String(seconds) : kind === 2 ? new Date(now + seconds * 1000).toUTCString() : "soon";
      const ms = retryDelayMs(failures, header, now, () => r);
      expect(ms).toBeGreaterThanOrEqual(0);
      expect(ms).toBeLessThanOrEqual(RETRY_CAP_MS);
      if (kind === 1 || kind === 2) {
        // The server's word, plus at most a quarter second of jitter (capped).
        expect(ms).toBeGreaterThanOrEqual(Math.min(RETRY_CAP_MS, seconds * 1000));
        expect(ms).toBeLessThanOrEqual(Math.min(RETRY_CAP_MS, seconds * 1000 + 250));
      } else {
        // No usable Retry-After: the upper half of 1 s doubling per failure.
        const ceiling = Math.min(30_000, 1000 * 2 ** failures);
        expect(ms).toBeGreaterThanOrEqual(Math.min(RETRY_CAP_MS, ceiling / 2));
        expect(ms).toBeLessThanOrEqual(Math.min(RETRY_CAP_MS, ceiling));
      }
    }
  });
});

describe("fetchRetrying", () => {
  it("asks again after each busy answer's Retry-After until the answer comes, for any run of 429s and 503s", async () => {
    const random = rng(11);
    for (let run = 0; run < 200; run++) {
      const refusals = Math.floor(random() * 8);
      const answers: Response[] = [];
      const expected: number[] = [];
      for (let i = 0; i < refusals; i++) {
        const seconds = 1 + Math.floor(random() * 5);
        answers.push(busy(random() < 0.5 ? 429 : 503, String(seconds)));
        expected.push(seconds * 1000);
      }
      answers.push(new Response("{}", { status: 200 }));
      const { clock, sleep, now } = fakeTime();
      const seen: Headers[] = [];
      const r = await fetchRetrying("/api/v1/robots", {}, {
        sleep, now, random: () => 0,
        fetchFn: async (_u, init) => { seen.push(new Headers(init?.headers)); return answers.shift()!; },
      });
      expect(r.status).toBe(200);
      expect(clock.waits).toEqual(expected);
      // Every attempt names this tab's session.
      expect(seen.every((h) => h.get(SESSION_HEADER) === SESSION_ID)).toBe(true);
    }
  });

  it("gives up after PATIENCE_MS with the last refusal, not after a count", async () => {
    const { clock, sleep, now } = fakeTime();
    let asked = 0;
    const r = await fetchRetrying("/x", {}, { sleep, now, random: () => 0.5, fetchFn: async () => { asked++; return busy(503, "7"); } });
    expect(r.status).toBe(503);
    expect(clock.now).toBeLessThanOrEqual(PATIENCE_MS);
    expect(clock.now).toBeGreaterThan(PATIENCE_MS - 8_000);
    expect(asked).toBeGreaterThan(10);
  });

  it("asks again while the server cannot be reached, and stops at once when aborted", async () => {
    const { sleep, now } = fakeTime();
    let asked = 0;
    const r = await fetchRetrying("/x", {}, {
      sleep, now, random: () => 0,
      fetchFn: async () => { if (++asked < 3) throw new TypeError("Failed to fetch"); return new Response("{}"); },
    });
    expect(r.status).toBe(200);
    expect(asked).toBe(3);

    const abort = new AbortController();
    let calls = 0;
    const waiting = fetchRetrying("/x", { signal: abort.signal }, {
      fetchFn: async () => { calls++; return busy(429, "30"); },
    });
    await new Promise((r) => setTimeout(r, 10));
    abort.abort();
    await expect(waiting).rejects.toMatchObject({ name: "AbortError" });
    expect(calls).toBe(1);
  });

  it("never retries an answer that is not busy", async () => {
    for (const status of [200, 204, 400, 401, 403, 404, 413, 422, 500, 502]) {
      let asked = 0;
      const r = await fetchRetrying("/x", {}, { fetchFn: async () => { asked++; return new Response(null, { status }); } });
      expect([r.status, asked]).toEqual([status, 1]);
      expect(BUSY.has(status)).toBe(false);
    }
  });
});

describe("sharedGet", () => {
  it("shares one request among identical reads in flight, and asks again once it is answered", async () => {
    const calls: string[] = [];
    let release!: () => void;
    const gate = new Promise<void>((r) => (release = r));
    vi.stubGlobal("fetch", async (url: string) => { calls.push(url); await gate; return new Response(`"${url}"`); });
    const reads = [sharedGet("/a"), sharedGet("/a"), sharedGet("/b"), sharedGet("/a")];
    expect(sharedInFlight()).toBe(2);
    release();
    const answers = await Promise.all(reads);
    expect(answers.map((a) => a.text)).toEqual(['"/a"', '"/a"', '"/b"', '"/a"']);
    expect(calls).toEqual(["/a", "/b"]);
    await sharedGet("/a");
    expect(calls).toEqual(["/a", "/b", "/a"]);
    expect(sharedInFlight()).toBe(0);
  });

  it("cancels the request only once every reader of it gave up, for any order of give-ups", async () => {
    const random = rng(5);
    for (let run = 0; run < 100; run++) {
      const readers = 1 + Math.floor(random() * 5);
      const quitting = Math.floor(random() * (readers + 1));
      let cancelled = false;
      let release!: () => void;
      const gate = new Promise<void>((r) => (release = r));
      vi.stubGlobal("fetch", async (_url: string, init: RequestInit) => {
        init.signal?.addEventListener("abort", () => (cancelled = true));
        await gate;
        return new Response("1");
      });
      const controllers = Array.from({ length: readers }, () => new AbortController());
      const reads = controllers.map((c) => sharedGet(`/r${run}`, c.signal).then(() => "answered", (e) => e.name));
      for (const c of controllers.slice(0, quitting)) c.abort();
      await new Promise((r) => setTimeout(r, 0));
      expect(cancelled).toBe(quitting === readers);
      release();
      const outcomes = await Promise.all(reads);
      expect(outcomes).toEqual(controllers.map((_, i) => (i < quitting ? "AbortError" : "answered")));
    }
  });
});

describe("what a failed read says", () => {
  it("tells what happened and what to do, in words, never a setting's name or a status line", () => {
    for (let status = 400; status < 600; status++) {
      const text = explainFailure("the map", status);
      expect(text).toContain("the map");
      expect(text).not.toMatch(/MAPSERVICE_|_[A-Z]{3,}|detail|\/api\//);
      // What to do: every message ends with an instruction.
      expect(text).toMatch(/(Reload|try again|Try again|enter|Pick|tell)/);
    }
  });

  it("getJson throws that text, keeping the server's own words apart", async () => {
    vi.stubGlobal("fetch", async () => new Response(JSON.stringify({ detail: "MAPSERVICE_X is 3" }), { status: 404 }));
    const e = (await getJson("/api/v1/map?at=1", "the map").catch((x: unknown) => x)) as ApiError;
    expect(e).toBeInstanceOf(ApiError);
    expect(e.status).toBe(404);
    expect(e.message).not.toContain("MAPSERVICE_X");
    expect(e.detail).toBe("MAPSERVICE_X is 3");
  });
});
