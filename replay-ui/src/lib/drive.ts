/**
 * Where the controller's robot may drive: not off the map and not into occupied pixels.
 *
 * The floor is the stitched map picture (one grey value per pixel, row 0 at the top, as the
 * map file). A pixel is occupied when darker than OCCUPIED_BELOW: ROS map_server's default
 * occupied_thresh of 0.65 on a trinary map (0 black = occupied, 205 = unknown, 254 = free).
 * The robot is a disc of ROBOT_RADIUS_M; a move is checked at every pixel along its way, so
 * a 0.5 m step cannot jump over a thin rack. A robot already standing on occupied pixels
 * (it painted the chunk under it black, or the map changed under it) may drive off them:
 * only a robot on free floor is stopped, so nobody is ever stuck.
 */
import { metresToPixel, pixelToMetres, resolutionOf } from "./geo";
import type { MapMeta } from "./types";

export const OCCUPIED_BELOW = 90; // (1 - 0.65) * 255, map_server's occupied threshold
export const ROBOT_RADIUS_M = 0.25;

export interface Floor {
  width: number;
  height: number;
  grey: Uint8Array; // width * height values, row 0 at the top
}

export type Blocked = { kind: "edge" } | { kind: "occupied"; row: number; col: number };

/** Why a robot centred at (x, y) metres cannot stand there, or null where it can. */
export function blockedAt(meta: MapMeta, floor: Floor | null, x: number, y: number, radiusM = ROBOT_RADIUS_M): Blocked | null {
  const res = resolutionOf(meta);
  const p = metresToPixel(meta, x, y);
  const r = radiusM / res;
  if (p.col - r < 0 || p.row - r < 0 || p.col + r > meta.width || p.row + r > meta.height) return { kind: "edge" };
  if (!floor) return null;
  const r2 = r * r;
  for (let row = Math.floor(p.row - r); row <= Math.ceil(p.row + r); row++) {
    if (row < 0 || row >= floor.height) continue;
    for (let col = Math.floor(p.col - r); col <= Math.ceil(p.col + r); col++) {
      if (col < 0 || col >= floor.width) continue;
      // The pixel's nearest point to the centre, so a disc touching a pixel counts.
      const dr = Math.max(row - p.row, 0, p.row - (row + 1));
      const dc = Math.max(col - p.col, 0, p.col - (col + 1));
      if (dr * dr + dc * dc < r2 && floor.grey[row * floor.width + col] < OCCUPIED_BELOW) return { kind: "occupied", row, col };
    }
  }
  return null;
}

/** A move from (x0, y0) to (x1, y1): where the robot ends (the start when stopped) and why it stopped. */
export function tryMove(meta: MapMeta, floor: Floor | null, x0: number, y0: number, x1: number, y1: number): { x: number; y: number; blocked: Blocked | null } {
  const res = resolutionOf(meta);
  const startBlocked = blockedAt(meta, floor, x0, y0);
  const steps = Math.max(1, Math.ceil(Math.hypot(x1 - x0, y1 - y0) / res));
  for (let i = 1; i <= steps; i++) {
    const x = x0 + ((x1 - x0) * i) / steps;
    const y = y0 + ((y1 - y0) * i) / steps;
    const b = blockedAt(meta, floor, x, y);
    // Off the map is never allowed; occupied pixels stop only a robot that stood free.
    if (b && (b.kind === "edge" || startBlocked === null)) return { x: x0, y: y0, blocked: b };
  }
  return { x: x1, y: y1, blocked: null };
}

/** The floor's grey values from the map picture (PNG), as the browser decodes it. */
export async function floorOfPicture(blob: Blob): Promise<Floor> {
  const bitmap = await createImageBitmap(blob);
  const canvas = new OffscreenCanvas(bitmap.width, bitmap.height);
  const ctx = canvas.getContext("2d")!;
  ctx.drawImage(bitmap, 0, 0);
  const rgba = ctx.getImageData(0, 0, bitmap.width, bitmap.height).data;
  const grey = new Uint8Array(bitmap.width * bitmap.height);
  for (let i = 0; i < grey.length; i++) grey[i] = rgba[i * 4];
  return { width: bitmap.width, height: bitmap.height, grey };
}

export function blockedText(b: Blocked, meta: MapMeta): string {
  if (b.kind === "edge") return "stopped: the map's edge";
  const at = pixelToMetres(meta, { row: b.row + 0.5, col: b.col + 0.5 });
  return `stopped: occupied floor at x ${at.x.toFixed(2)} m, y ${at.y.toFixed(2)} m`;
}

/** The free spot nearest to (x, y) on a grid of `step` metres (the robot's start), or (x, y). */
export function nearestFree(meta: MapMeta, floor: Floor | null, x: number, y: number, step: number): { x: number; y: number } {
  for (let ring = 0; ring < 200; ring++) {
    for (let i = -ring; i <= ring; i++) {
      for (const [dx, dy] of [[i, -ring], [i, ring], [-ring, i], [ring, i]]) {
        const cx = x + dx * step;
        const cy = y + dy * step;
        if (!blockedAt(meta, floor, cx, cy)) return { x: cx, y: cy };
      }
    }
  }
  return { x, y };
}
