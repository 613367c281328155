/** The 2019 REST contract (appendix A) as the controller page speaks it, like a robot. */
import { quaternionOfYaw } from "./geo";
import type { MapMeta } from "./types";
import { ApiError, getJson, send } from "./request";

/** "2018-12-20T23:34:33": the 2019 timestamp format (UTC, seconds). */
export function timestamp2019(ms: number): string {
  return new Date(ms).toISOString().slice(0, 19);
}

/** zlib (RFC 1950) stream of the bytes, base64: the 2019 `pgmB64compressedData`. */
export async function pgmB64compressed(pixels: Uint8Array): Promise<string> {
  const stream = new Blob([pixels as unknown as ArrayBuffer]).stream().pipeThrough(new CompressionStream("deflate"));
  const bytes = new Uint8Array(await new Response(stream).arrayBuffer());
  let s = "";
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
  return btoa(s);
}

/** Listing 14: one chunk filled with `value`, as POSTed or published on iot/chunks/create. */
export async function chunkMessage(meta: MapMeta, robotId: string, row: number, column: number, value: number, nowMs: number) {
  const pixels = new Uint8Array(meta.CHUNK_WIDTH * meta.CHUNK_HEIGHT).fill(value);
  return { pgmB64compressedData: await pgmB64compressed(pixels), row, column, timestamp: timestamp2019(nowMs), robotId };
}

/** POST /api/chunk-service/chunks as a robot does, through the page's request layer (a busy
 * server is asked again after its Retry-After; the write is refused then, never half done);
 * a refusal is an ApiError with the server's words. */
export async function postChunk(message: object, base = ""): Promise<void> {
  await send("POST", `${base}/api/chunk-service/chunks`, message);
}

/** Listing 16, the body a robot publishes on iot/coordinates/{robotId}. */
export function poseMessage(robotId: string, x: number, y: number, yaw: number, nowMs: number, battery: number) {
  const [qx, qy, qz, qw] = quaternionOfYaw(yaw);
  return {
    robotId,
    timestamp: timestamp2019(nowMs),
    pose: { position: { x, y, z: 0 }, orientation: { x: qx, y: qy, z: qz, w: qw } },
    status: { battery: { battery_level: battery, charging: false }, loaded: false },
  };
}

/** The map's meta (null: none stored yet): the 2019 endpoint's, else the map's resolved one
 * (a 2019 meta may lack the chunk size). Any other failure is an ApiError in a user's words. */
export async function getMeta(base = ""): Promise<MapMeta | null> {
  try {
    const m = await getJson<Partial<MapMeta> | null>(`${base}/api/chunk-service/meta`, "the map's meta");
    if (m && m.CHUNK_WIDTH) return m as MapMeta;
  } catch (e) {
    if (!(e instanceof ApiError && e.status === 404)) throw e;
  }
  return (await getJson<{ meta: MapMeta | null }>(`${base}/api/v1/map`, "the map")).meta;
}
