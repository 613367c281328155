/** Shapes of the mapservice API (/api/v1) as the UI consumes them. */

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

export interface ChunkCell {
  row: number;
  column: number;
  ts_ms: number;
  robotId: string;
  content_hash: string;
}

/** One chunk write; `prev` is the cell's state just before it (null: never written). */
export interface ChunkChange extends ChunkCell {
  prev?: ChunkCell | null;
}

export interface Pose {
  robotId: string;
  ts_ms: number;
  receive_time_ms?: number;
  position: [number, number, number];
  orientation: [number, number, number, number];
  battery_level: number | null;
  charging: boolean | string | null;
  loaded: boolean | string | null;
  path: [number, number][] | null;
}

export interface RobotAt extends Pose {
  age_ms?: number;
  online?: boolean;
  clock_skew_ms?: number;
  clock_skew_flag?: boolean;
}

export interface EventWindow {
  from_ms: number;
  to_ms: number;
  step_ms: number;
  chunks: ChunkChange[];
  poses: Pose[];
  truncated: boolean;
}

export interface TimelineBucket {
  start_ms: number;
  chunk_changes: number;
  conflicts: number;
  robots_active: number;
}

export interface Timeline {
  from_ms: number;
  to_ms: number;
  bucket_ms: number;
  buckets: TimelineBucket[];
}

export interface Conflict {
  row: number;
  column: number;
  ts_ms: number;
  robot_a: string;
  robot_b: string;
  hash_a?: string;
  hash_b?: string;
}
