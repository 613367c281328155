import { readdirSync, readFileSync, statSync } from "node:fs";
import { join } from "node:path";
import { afterEach, describe, expect, it, vi } from "vitest";
import { getClientConfig } from "../src/lib/robotlink";
import { getMeta, postChunk } from "../src/lib/legacy";
import { ApiError, getBlob, SESSION_HEADER, SESSION_ID, Superseding } from "../src/lib/request";

afterEach(() => vi.unstubAllGlobals());

interface Asked {
  url: string;
  method: string;
  session: string | null;
  body: unknown;
}

/** A server that answers each request with the next of `answers` (a status, or a status
 * and a body), recording what was asked; a busy answer says to come back at once. */
function server(answers: [number, unknown?][]): Asked[] {
  const asked: Asked[] = [];
  vi.stubGlobal("fetch", async (url: string, init: RequestInit = {}) => {
    if (init.signal?.aborted) throw new DOMException("The read was cancelled", "AbortError"); // as fetch does
    asked.push({ url, method: init.method ?? "GET", session: new Headers(init.headers).get(SESSION_HEADER), body: init.body });
    const [status, body] = answers.shift() ?? [500];
    const headers: Record<string, string> = status === 429 || status === 503 ? { "Retry-After": "0" } : {};
    return new Response(body === undefined ? null : JSON.stringify(body), { status, headers });
  });
  return asked;
}

const CONFIG = { mqtt_ws_url: "ws://h/mqtt", coordinate_topic_prefix: "iot/coordinates/", create_chunk_topic: "iot/chunks/create", robot_chunk_topic_prefix: null };
const META = { CHUNK_WIDTH: 100, CHUNK_HEIGHT: 100, width: 400, height: 300, resolution: 0.05, origin: [0, 0, 0] };

describe("the controller page's requests go through the page's request layer", () => {
  it("reads the client config with the session header, waiting out a busy server", async () => {
    const asked = server([[429], [503], [200, CONFIG]]);
    expect(await getClientConfig()).toEqual(CONFIG);
    expect(asked.map((a) => [a.url, a.session])).toEqual(Array(3).fill(["/api/v1/client-config", SESSION_ID]));
  });

  it("says what to do when the client config is refused, in words, not a status line", async () => {
    server([[401, { detail: "missing token" }]]);
    const e = await getClientConfig().catch((x) => x);
    expect(e).toBeInstanceOf(ApiError);
    expect(e.message).toMatch(/API token/);
    expect(e.message).not.toMatch(/401|MAPSERVICE_/);
  });

  it("reads the meta from the 2019 endpoint, else the map's; none stored is null, not an error", async () => {
    let asked = server([[200, META]]);
    expect(await getMeta()).toEqual(META);
    expect(asked.map((a) => a.url)).toEqual(["/api/chunk-service/meta"]);
    asked = server([[404, { detail: "no meta" }], [200, { meta: META, chunks: [] }]]);
    expect(await getMeta()).toEqual(META);
    expect(asked.map((a) => [a.url, a.session])).toEqual([["/api/chunk-service/meta", SESSION_ID], ["/api/v1/map", SESSION_ID]]);
    server([[404, { detail: "no meta" }], [200, { meta: null, chunks: [] }]]);
    expect(await getMeta()).toBeNull();
    server([[500, { detail: "boom" }]]);
    await expect(getMeta()).rejects.toBeInstanceOf(ApiError);
  });

  it("posts a chunk with the session header, the same body again after a busy answer", async () => {
    const asked = server([[429], [201, { id: "x" }]]);
    await postChunk({ row: 1, column: 2 });
    expect(asked.map((a) => [a.method, a.url, a.session, a.body])).toEqual(
      Array(2).fill(["POST", "/api/chunk-service/chunks", SESSION_ID, JSON.stringify({ row: 1, column: 2 })]));
  });

  it("says why a chunk was refused in the server's words, with its status for the token case", async () => {
    server([[422, { detail: "row 99 is outside the 16 x 12 chunk grid" }]]);
    await expect(postChunk({ row: 99, column: 2 })).rejects.toMatchObject({ status: 422, message: "422: row 99 is outside the 16 x 12 chunk grid" });
    server([[401, { detail: "a writer token is needed" }]]);
    await expect(postChunk({ row: 1, column: 2 })).rejects.toMatchObject({ status: 401 });
  });

  it("reads a picture's bytes with the session header; a newer read cancels the older", async () => {
    const asked = server([[200, "png"]]);
    expect(await (await getBlob("/api/v1/map/png", "the floor's picture")).text()).toBe('"png"');
    expect(asked[0].session).toBe(SESSION_ID);
    const reads = new Superseding();
    const first = reads.next();
    const second = reads.next();
    expect([first.aborted, second.aborted]).toEqual([true, false]);
    await expect(getBlob("/api/v1/map/png", "the floor's picture", first)).rejects.toMatchObject({ name: "AbortError" });
    reads.cancel();
    expect(second.aborted).toBe(true);
  });

  it("leaves fetch to lib/request.ts: no other module of the pages calls it", () => {
    const root = join(__dirname, "..", "src");
    const files: string[] = [];
    const walk = (dir: string) => {
      for (const name of readdirSync(dir)) {
        const path = join(dir, name);
        if (statSync(path).isDirectory()) walk(path);
        else if (/\.(ts|vue)$/.test(name) && !name.endsWith(".d.ts")) files.push(path);
      }
    };
    walk(root);
    const calling = files.filter((f) => !f.endsWith(join("lib", "request.ts")) && /(^|[^\w.])fetch\s*\(/m.test(readFileSync(f, "utf8")));
    expect(calling.map((f) => f.slice(root.length + 1))).toEqual([]);
  });
});
