import { deflateSync } from "node:zlib";
import { encode } from "@msgpack/msgpack";
import { afterEach, describe, expect, it, vi } from "vitest";
import { Api, ApiError } from "../src/lib/api";
import { BATCH_MAX, greyToRgba, inflate, parseBatch, slicesFor, type ChunkBatch, type ChunkContent } from "../src/lib/chunkdecode";
import { ChunkImages, type ChunkImage, type ChunkSource } from "../src/lib/images";

const hex = (i: number) => i.toString(16).padStart(32, "0");
const BROKEN = "f".repeat(32);
const settle = () => new Promise((r) => setTimeout(r, 0));

afterEach(() => vi.unstubAllGlobals());

describe("chunk batch decoding", () => {
  it("inflates zlib as the robot sent it", () => {
    const grey = Uint8Array.from({ length: 10_000 }, (_, i) => i % 256);
    expect(inflate(new Uint8Array(deflateSync(grey)))).toEqual(grey);
    expect(() => inflate(Uint8Array.from([1, 2, 3]))).toThrow();
  });

  it("maps PGM grey levels to opaque greys like the PNG path", () => {
    const rgba = greyToRgba(Uint8Array.from([0, 205, 254, 255]), 2, 2);
    expect(Array.from(rgba)).toEqual([0, 0, 0, 255, 205, 205, 205, 255, 254, 254, 254, 255, 255, 255, 255, 255]);
    expect(() => greyToRgba(new Uint8Array(3), 2, 2)).toThrow(/expected 2x2/);
  });

  it("parses the MessagePack answer", () => {
    const z = new Uint8Array(deflateSync(Buffer.from([1, 2])));
    const body = encode({ contents: [[hex(1), 2, 1, z]], missing: [hex(2)] });
    expect(parseBatch(body)).toEqual({ contents: [{ hash: hex(1), width: 2, height: 1, zlib: z }], missing: [hex(2)] });
    expect(() => parseBatch(encode([1, 2]))).toThrow(/contents, missing/);
  });

  it("cuts hashes into about `parallel` slices within the bounds", () => {
    const hs = Array.from({ length: 1000 }, (_, i) => hex(i));
    expect(slicesFor(hs, 4).map((s) => s.length)).toEqual([250, 250, 250, 250]);
    expect(slicesFor(hs.slice(0, 10), 4).map((s) => s.length)).toEqual([10]);
    expect(slicesFor(hs, 1).every((s) => s.length <= 512)).toBe(true);
    expect(slicesFor(hs, 1, 1, 5000)[0].length).toBeLessThanOrEqual(BATCH_MAX);
    expect(slicesFor(hs, 3).flat()).toEqual(hs);
  });

  it("Api.chunkBatch posts the hashes and decodes the answer; errors carry the status", async () => {
    const calls: { url: string; body: string }[] = [];
    vi.stubGlobal("fetch", async (url: string, init: RequestInit) => {
      calls.push({ url, body: init.body as string });
      if (url.startsWith("/refusing")) return new Response("", { status: 405, statusText: "Method Not Allowed" });
      return new Response(encode({ contents: [], missing: [hex(3)] }), { status: 200 });
    });
    expect(await new Api().chunkBatch([hex(3)])).toEqual({ contents: [], missing: [hex(3)] });
    expect(calls[0]).toEqual({ url: "/api/v1/chunk-contents/batch", body: JSON.stringify({ hashes: [hex(3)] }) });
    await expect(new Api("/refusing").chunkBatch([hex(3)])).rejects.toMatchObject({ status: 405 });
  });
});

class FakeSource implements ChunkSource {
  batches: string[][] = [];
  constructor(public known: Set<string>, public batchError: Error | null = null) {}
  async chunkBatch(hashes: string[]): Promise<ChunkBatch> {
    this.batches.push(hashes);
    if (this.batchError) throw this.batchError;
    return {
      contents: hashes.filter((h) => this.known.has(h)).map((hash) => ({ hash, width: 1, height: 1, zlib: new Uint8Array() })),
      missing: hashes.filter((h) => !this.known.has(h)),
    };
  }
}

const fakeImage = (name: string) => ({ name }) as unknown as ChunkImage;

function images(source: FakeSource, opts = {}) {
  const loaded: string[][] = [];
  const im = new ChunkImages(source, {
    decode: (c: ChunkContent) => {
      if (c.hash === BROKEN) throw new Error("bad zlib");
      return fakeImage(c.hash);
    },
    ...opts,
  });
  im.onLoad = (hs) => loaded.push(hs);
  return { im, loaded };
}

describe("ChunkImages", () => {
  it("fetches what one task asks for in a few parallel batches, each hash once", async () => {
    const hs = Array.from({ length: 1000 }, (_, i) => hex(i));
    const src = new FakeSource(new Set(hs));
    const { im, loaded } = images(src, { parallel: 4 });
    for (const h of hs) im.request(h, true);
    im.requestMany(hs);
    await settle();
    expect(src.batches.map((b) => b.length)).toEqual([250, 250, 250, 250]);
    expect(new Set(src.batches.flat()).size).toBe(1000);
    expect(im.fetched).toBe(1000);
    expect(im.requests).toBe(4);
    expect(loaded.flat().sort()).toEqual([...hs].sort());
    expect(im.get(hs[7])).toEqual(fakeImage(hs[7]));
    im.requestMany(hs);
    await settle();
    expect(src.batches).toHaveLength(4); // all cached
  });

  it("marks hashes the server lists missing as failed, and does not ask again", async () => {
    const src = new FakeSource(new Set([hex(1)]));
    const { im } = images(src);
    im.requestMany([hex(1), hex(2)]);
    await settle();
    expect(im.has(hex(1))).toBe(true);
    expect(im.failed.has(hex(2))).toBe(true);
    im.request(hex(2), true);
    await settle();
    expect(src.batches).toHaveLength(1);
  });

  it("fails only the pictures that do not decode", async () => {
    const src = new FakeSource(new Set([hex(1), BROKEN]));
    const { im, loaded } = images(src);
    im.requestMany([hex(1), BROKEN]);
    await settle();
    expect(loaded).toEqual([[hex(1)]]);
    expect(im.failed.has(BROKEN)).toBe(true);
  });

  it("fails a batch's hashes on other errors instead of waiting for them forever", async () => {
    // A 404 or 405 too: the page's own server has the batch endpoint, so nothing else is asked.
    const fetched: string[] = [];
    vi.stubGlobal("fetch", async (url: string) => {
      fetched.push(url);
      return new Response("", { status: 404 });
    });
    for (const status of [404, 405, 500]) {
      const src = new FakeSource(new Set([hex(1)]), new ApiError(status, "no"));
      const { im } = images(src);
      im.requestMany([hex(1)]);
      await settle();
      await settle();
      expect(im.failed.has(hex(1))).toBe(true);
      expect(im.queued).toBe(0);
      expect(src.batches).toHaveLength(1);
    }
    expect(fetched).toEqual([]);
  });

  it("asks again later for pictures a busy (or unreachable) server did not send", async () => {
    for (const status of [429, 503, 0]) {
      const src = new FakeSource(new Set([hex(1)]), new ApiError(status, "busy"));
      const { im, loaded } = images(src);
      im.requestMany([hex(1)]);
      await settle();
      await settle();
      expect(im.failed.has(hex(1))).toBe(false);
      expect(im.queued).toBe(0);
      src.batchError = null; // the server has time again: the next want of it asks
      im.requestMany([hex(1)]);
      await settle();
      await settle();
      expect(src.batches).toHaveLength(2);
      expect(loaded.flat()).toEqual([hex(1)]);
    }
  });

  it("appends prefetches behind what is queued, and urgent requests jump ahead", async () => {
    const src = new FakeSource(new Set([hex(1), hex(2), hex(3)]));
    const { im } = images(src, { parallel: 1 });
    im.requestMany([hex(1)]);
    im.requestMany([hex(2)], false);
    im.request(hex(3), true);
    await settle();
    expect(src.batches[0]).toEqual([hex(3), hex(1), hex(2)]);
  });

  it("evicts least recently used pictures past its capacity", async () => {
    const src = new FakeSource(new Set([hex(1), hex(2), hex(3)]));
    const { im } = images(src, { capacity: 2, parallel: 1 });
    im.requestMany([hex(1), hex(2)]);
    await settle();
    im.get(hex(1));
    im.requestMany([hex(3)]);
    await settle();
    expect([im.has(hex(1)), im.has(hex(2)), im.has(hex(3))]).toEqual([true, false, true]);
  });
});
