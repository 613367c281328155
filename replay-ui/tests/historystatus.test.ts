import { describe, expect, it } from "vitest";
import { bannerFor, pollStatus, utcClock, type HistoryStatus } from "../src/lib/historystatus";
import { SESSION_HEADER, SESSION_ID } from "../src/lib/request";

const SINCE = Date.UTC(2026, 10, 25, 22, 15, 3, 400);
const failing: HistoryStatus = {
  storing: false, failing_since_ms: SINCE, last_stored_ms: SINCE - 200,
  reason: "inserts failing since 22:15:03Z (3 attempts): NOT_ENOUGH_SPACE: Code: 243. ...",
};

describe("bannerFor", () => {
  it("says since when the history is not stored, in UTC, with the server's reason", () => {
    const b = bannerFor(failing)!;
    expect(b.text).toBe("history not stored since 22:15:03 UTC");
    expect(b.title).toContain("NOT_ENOUGH_SPACE");
    expect(b.title).toContain("Nothing acknowledged is lost");
  });

  it("shows nothing while the history is stored, or where the API cannot know", () => {
    expect(bannerFor({ ...failing, storing: true, failing_since_ms: null, reason: null })).toBeNull();
    expect(bannerFor(null)).toBeNull();
    expect(bannerFor(undefined)).toBeNull();
  });

  it("falls back to the last stored insert, then to no time at all", () => {
    expect(bannerFor({ ...failing, failing_since_ms: null })!.text).toBe("history not stored since 22:15:03 UTC");
    expect(bannerFor({ ...failing, failing_since_ms: null, last_stored_ms: null, reason: null })).toEqual({
      text: "history not stored",
      title: "the server refuses to store new events. Nothing acknowledged is lost: the events wait and are stored once the server recovers.",
    });
  });

  it("formats a clock time in UTC whatever the browser's zone", () => {
    expect(utcClock(Date.UTC(2026, 0, 1, 3, 4, 5))).toBe("03:04:05 UTC");
  });
});

describe("pollStatus", () => {
  const reply = (status: number, body: unknown) =>
    (async () => new Response(JSON.stringify(body), { status })) as unknown as typeof fetch;
  /** The request layer's options with a clock its waits advance (a busy answer is waited for). */
  const via = (fetchFn: typeof fetch) => {
    let now = 0;
    return { fetchFn, now: () => now, sleep: async (ms: number) => void (now += ms) };
  };

  it("reads the history's status from /api/v1/status", async () => {
    const urls: string[] = [];
    const sessions: (string | null)[] = [];
    const fetchFn = (async (url: string, init: RequestInit) => {
      urls.push(url);
      sessions.push(new Headers(init.headers).get(SESSION_HEADER));
      return new Response(JSON.stringify({ history: failing }), { status: 200 });
    }) as unknown as typeof fetch;
    expect(await pollStatus("http://h", via(fetchFn))).toEqual({ history: failing });
    expect(urls).toEqual(["http://h/api/v1/status"]);
    expect(sessions).toEqual([SESSION_ID]);
  });

  it("an API apart from the processors answers null: no banner", async () => {
    const got = await pollStatus("", via(reply(200, { history: null })));
    expect(got).toEqual({ history: null });
    expect(bannerFor((got as { history: HistoryStatus | null }).history)).toBeNull();
  });

  it("learns nothing from a failure, a 404 included, and is asked again next time", async () => {
    for (const status of [404, 500, 503]) expect(await pollStatus("", via(reply(status, { detail: "no" })))).toBe("unknown");
    const down = (async () => { throw new TypeError("Failed to fetch"); }) as unknown as typeof fetch;
    expect(await pollStatus("", via(down))).toBe("unknown");
  });
});
