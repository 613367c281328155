/**
 * The conflict inspector's list (GET /api/v1/conflicts: both writes of each conflict, where
 * to seek) and the export button's download (GET /api/v1/exports/...), with the token the
 * page holds for reads (lib/auth.ts): a link cannot carry an Authorization header, so the
 * file is fetched and handed to the browser as a download.
 */
import { getJson } from "./api";
import { fetchRetrying } from "./request";

export interface ConflictEntry {
  row: number;
  column: number;
  ts_ms: number; // the later write's (robot_b's) event time
  robot_a: string;
  ts_a_ms: number;
  hash_a: string | null;
  robot_b: string;
  hash_b: string | null;
  seek_ms: number; // just after the later write
}

export interface ConflictList {
  from_ms: number;
  to_ms: number;
  window_s: number;
  rule: string;
  conflicts: ConflictEntry[];
  truncated: boolean;
}

async function failure(what: string, r: Response): Promise<Error> {
  let detail = r.statusText;
  try {
    const body = await r.json();
    detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail ?? body);
  } catch {
    /* not JSON */
  }
  if (r.status === 401 || r.status === 403) detail += " (reads need an API token here: enter one in the token box)";
  return new Error(`${what}: ${r.status} ${detail}`);
}

export async function fetchConflictList(base: string, fromMs: number, toMs: number, limit = 500): Promise<ConflictList> {
  const q = new URLSearchParams({ from: String(Math.floor(fromMs)), to: String(Math.ceil(toMs)), limit: String(limit) });
  return getJson<ConflictList>(`${base}/api/v1/conflicts?${q}`, "the conflicts");
}

export function conflictKey(c: ConflictEntry): string {
  return `${c.ts_ms}:${c.row}:${c.column}:${c.robot_b}`;
}

/** "12.3 s" between the two writes. */
export function gapText(c: ConflictEntry): string {
  return `${((c.ts_ms - c.ts_a_ms) / 1000).toFixed(1)} s`;
}

/** What the MCAP holds, for the button's title. */
export const MCAP_CONTENTS = "the map (foxglove.Grid), each robot's pose, battery in %, charging, loaded and planned path, the annotations (foxglove.SceneUpdate) and the commands";

export type ExportKind = "mcap" | "robot-poses" | "chunk-changes" | "chunk-conflicts";

export const EXPORTS: { kind: ExportKind; label: string; maxSpanMs: number }[] = [
  { kind: "mcap", label: "MCAP (Foxglove)", maxSpanMs: 86_400_000 },
  { kind: "robot-poses", label: "CSV: robot poses", maxSpanMs: 7 * 86_400_000 },
  { kind: "chunk-changes", label: "CSV: chunk changes", maxSpanMs: 7 * 86_400_000 },
  { kind: "chunk-conflicts", label: "CSV: conflicts", maxSpanMs: 7 * 86_400_000 },
];

export function exportUrl(base: string, kind: ExportKind, fromMs: number, toMs: number): string {
  const q = new URLSearchParams({ from: String(Math.floor(fromMs)), to: String(Math.ceil(toMs)) });
  if (kind === "mcap") return `${base}/api/v1/exports/replay.mcap?${q}`;
  q.set("format", "csv");
  return `${base}/api/v1/exports/tables/${kind}?${q}`;
}

/** The file name the server gives (Content-Disposition), or a fallback. */
export function fileNameOf(r: Response, fallback: string): string {
  const m = /filename="([^"]+)"/.exec(r.headers.get("Content-Disposition") ?? "");
  return m ? m[1] : fallback;
}

/** Fetches an export (with the read token) and saves it; resolves to its name and size in bytes. */
export async function downloadExport(base: string, kind: ExportKind, fromMs: number, toMs: number): Promise<{ name: string; bytes: number }> {
  const r = await fetchRetrying(exportUrl(base, kind, fromMs, toMs));
  if (!r.ok) throw await failure("export", r);
  const blob = await r.blob();
  const name = fileNameOf(r, kind === "mcap" ? "replay.mcap" : `${kind}.csv`);
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = name;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
  return { name, bytes: blob.size };
}

/** "1.2 MB" */
export function sizeText(bytes: number): string {
  if (bytes < 1024) return `${bytes} B`;
  if (bytes < 1024 * 1024) return `${(bytes / 1024).toFixed(1)} kB`;
  return `${(bytes / 1024 / 1024).toFixed(1)} MB`;
}
