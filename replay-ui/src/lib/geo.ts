/**
 * Metres <-> map pixels <-> Leaflet (L.CRS.Simple) coordinates.
 *
 * ROS map_server convention: `origin` is the world pose of the image's lower-left pixel and
 * `resolution` is metres per pixel; image row 0 is the top. Leaflet's simple CRS has y
 * growing upwards, so a pixel (row, col) is drawn at latlng (-row, col): the map sits in the
 * fourth quadrant with its top-left corner at (0, 0).
 */
import type { MapMeta } from "./types";

/** What a 2019 meta (no resolution/origin) is drawn with: map_server's common 5 cm grid. */
export const DEFAULT_RESOLUTION = 0.05;

export interface Pixel {
  row: number; // from the top of the image, fractional
  col: number;
}

export function resolutionOf(meta: MapMeta): number {
  return meta.resolution && meta.resolution > 0 ? meta.resolution : DEFAULT_RESOLUTION;
}

export function originOf(meta: MapMeta): [number, number] {
  const o = meta.origin;
  return o ? [o[0], o[1]] : [0, 0];
}

export function metresToPixel(meta: MapMeta, x: number, y: number): Pixel {
  const res = resolutionOf(meta);
  const [ox, oy] = originOf(meta);
  return { col: (x - ox) / res, row: meta.height - (y - oy) / res };
}

export function pixelToMetres(meta: MapMeta, p: Pixel): { x: number; y: number } {
  const res = resolutionOf(meta);
  const [ox, oy] = originOf(meta);
  return { x: ox + p.col * res, y: oy + (meta.height - p.row) * res };
}

/** [lat, lng] for L.CRS.Simple. */
export function pixelToLatLng(p: Pixel): [number, number] {
  return [-p.row, p.col];
}

export function latLngToPixel(lat: number, lng: number): Pixel {
  return { row: -lat, col: lng };
}

export function metresToLatLng(meta: MapMeta, x: number, y: number): [number, number] {
  return pixelToLatLng(metresToPixel(meta, x, y));
}

/** The chunk (row, column) holding a point in metres, or null outside the grid. */
export function chunkAt(meta: MapMeta, x: number, y: number): { row: number; column: number } | null {
  const p = metresToPixel(meta, x, y);
  const row = Math.floor(p.row / meta.CHUNK_HEIGHT);
  const column = Math.floor(p.col / meta.CHUNK_WIDTH);
  if (row < 0 || column < 0 || row >= meta.CHUNK_ROWS || column >= meta.CHUNK_COLS) return null;
  return { row, column };
}

/** Pixel bounds of a chunk: [[lat, lng] of the top-left, [lat, lng] of the bottom-right]. */
export function chunkBounds(meta: MapMeta, row: number, column: number): [[number, number], [number, number]] {
  const top = row * meta.CHUNK_HEIGHT;
  const left = column * meta.CHUNK_WIDTH;
  return [
    [-top, left],
    [-(top + meta.CHUNK_HEIGHT), left + meta.CHUNK_WIDTH],
  ];
}

/** Bounds of the whole chunk grid (may exceed width/height: the last chunks are padded). */
export function gridBounds(meta: MapMeta): [[number, number], [number, number]] {
  return [
    [0, 0],
    [-meta.CHUNK_ROWS * meta.CHUNK_HEIGHT, meta.CHUNK_COLS * meta.CHUNK_WIDTH],
  ];
}

/** Heading (rad, counter-clockwise from +x) of a quaternion [x, y, z, w]. */
export function yawOf(q: readonly number[]): number {
  const [x, y, z, w] = q;
  return Math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z));
}

export function quaternionOfYaw(yaw: number): [number, number, number, number] {
  return [0, 0, Math.sin(yaw / 2), Math.cos(yaw / 2)];
}
