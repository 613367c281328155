/**
 * Chunk pictures from `POST /api/v1/chunk-contents/batch`: a MessagePack map
 * `{contents: [[hash, width, height, zlib pixels], ...], missing: [hash, ...]}`, the pixels
 * zlib-compressed PGM grey levels exactly as the robot sent them.
 */
import { decode } from "@msgpack/msgpack";
import { unzlibSync } from "fflate";

export interface ChunkContent {
  hash: string;
  width: number;
  height: number;
  zlib: Uint8Array;
}

export interface ChunkBatch {
  contents: ChunkContent[];
  missing: string[];
}

/** The batch endpoint's limit (api/routers/chunk_contents.py BATCH_MAX). */
export const BATCH_MAX = 2000;

export function parseBatch(body: ArrayBuffer | Uint8Array): ChunkBatch {
  const raw = decode(body instanceof Uint8Array ? body : new Uint8Array(body)) as {
    contents?: [string, number, number, Uint8Array][];
    missing?: string[];
  };
  if (!raw || !Array.isArray(raw.contents) || !Array.isArray(raw.missing)) throw new Error("chunk batch: not a {contents, missing} map");
  return {
    contents: raw.contents.map(([hash, width, height, zlib]) => ({ hash, width, height, zlib })),
    missing: raw.missing,
  };
}

/**
 * zlib (RFC 1950) to raw bytes, synchronously: a seek's few dozen chunks inflate in about a
 * millisecond in the task that received them, where DecompressionStream plus
 * createImageBitmap took tens of milliseconds of task hops while the page drew frames.
 */
export function inflate(zlib: Uint8Array): Uint8Array {
  return unzlibSync(zlib);
}

/**
 * Grey levels to RGBA, as the PNG path shows them: each level is its own grey
 * (0 black = occupied, 205 grey = unknown, 254/255 white = free), opaque.
 */
export function greyToRgba(grey: Uint8Array, width: number, height: number): Uint8ClampedArray<ArrayBuffer> {
  const n = width * height;
  if (grey.length !== n) throw new Error(`chunk has ${grey.length} pixels, expected ${width}x${height}`);
  const out = new Uint8ClampedArray(n * 4);
  // One 32-bit store per pixel; the byte order of RGBA in memory is the platform's.
  const words = new Uint32Array(out.buffer);
  const little = new Uint8Array(new Uint32Array([1]).buffer)[0] === 1;
  for (let i = 0; i < n; i++) {
    const v = grey[i];
    words[i] = little ? (0xff000000 | (v << 16) | (v << 8) | v) >>> 0 : ((v << 24) | (v << 16) | (v << 8) | 0xff) >>> 0;
  }
  return out;
}

/** Hashes in slices for the batch endpoint: about `parallel` slices, each within [min, max]. */
export function slicesFor(hashes: string[], parallel: number, min = 32, max = 512): string[][] {
  const size = Math.max(min, Math.min(max, BATCH_MAX, Math.ceil(hashes.length / Math.max(1, parallel))));
  const out: string[][] = [];
  for (let i = 0; i < hashes.length; i += size) out.push(hashes.slice(i, i + size));
  return out;
}
