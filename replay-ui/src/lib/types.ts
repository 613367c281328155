/**
 * Shapes of the mapservice API (/api/v1) as the UI consumes them.
 *
 * The response shapes come from the API's OpenAPI document: api-schema.d.ts is generated from
 * it (`make api-types`; tests/api/test_ui_api_types.py fails when it is out of date), so a
 * route that changes a field changes these types and the build shows every use it breaks.
 * Written here by hand: what the API does not describe (the map meta, a free-form object in
 * its document) and what only the UI adds (a chunk change's previous state).
 */

import type { components } from "./api-schema";

type Schemas = components["schemas"];

/** The map meta (meta.json of the 2019 contract): the API serves it as a free-form object. */
export interface MapMeta {
  width: number;
  height: number;
  CHUNK_WIDTH: number;
  CHUNK_HEIGHT: number;
  CHUNK_ROWS: number;
  CHUNK_COLS: number;
  comment?: string;
  max_brightness?: string;
  resolution?: number;
  origin?: [number, number, number];
}

/** A chunk cell's last write (GET /api/v1/map's chunks); the UI never reads the ISO time. */
export type ChunkCell = Omit<Schemas["ChunkAt"], "timestamp">;

/** One chunk write; `prev` is the cell's state just before it (null: never written), which
 * the UI works out itself (buffer.ts) to step backwards. */
export interface ChunkChange extends ChunkCell {
  prev?: ChunkCell | null;
}

/** A pose (GET /api/v1/events, the live WebSocket); the UI never reads the ISO time, and a
 * live frame may come without the gateway's receive time. */
export type Pose = Omit<Schemas["Pose"], "timestamp" | "receive_time_ms"> &
  Partial<Pick<Schemas["Pose"], "receive_time_ms">>;

/** A robot at an instant (GET /api/v1/robots); the UI also makes one from a live pose, which
 * has no age, online flag or clock skew. */
export type RobotAt = Pose &
  Partial<Pick<Schemas["RobotAt"], "age_ms" | "online" | "clock_skew_ms" | "clock_skew_flag">>;

/** An event window (GET /api/v1/events), its chunks as the UI keeps them. */
export type EventWindow = Omit<Schemas["Events"], "chunks" | "poses" | "chunk_step_ms"> &
  Partial<Pick<Schemas["Events"], "chunk_step_ms">> & {
    chunks: ChunkChange[];
    poses: Pose[];
  };

/** One bucket of GET /api/v1/timeline. */
export type TimelineBucket = Schemas["Bucket"];

/** GET /api/v1/timeline. */
export type Timeline = Schemas["Timeline"];

/** A conflict (GET /api/v1/conflicts). */
export type Conflict = Schemas["Conflict"];

/** One robot's track aggregated per time bucket from every pose (the plots' read). */
export type TrackBuckets = Schemas["TrackBuckets"];
export type TrackBucket = Schemas["TrackBucket"];
