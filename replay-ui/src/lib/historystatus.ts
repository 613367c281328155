/**
 * Whether the service is storing history now (GET /api/v1/status): while ClickHouse
 * refuses inserts (a full disk, ...) the replay would show a past that silently stops, so
 * the page says "history not stored since HH:MM:SS UTC", with the server's reason.
 */
import { sharedGet, type FetchOptions } from "./request";

/** /api/v1/status's `history`: null where the API runs apart from the processors. */
export interface HistoryStatus {
  storing: boolean;
  failing_since_ms: number | null;
  last_stored_ms: number | null;
  reason: string | null;
}

export interface Banner {
  text: string;
  title: string;
}

/** "22:15:03 UTC" */
export function utcClock(ms: number): string {
  return `${new Date(ms).toISOString().slice(11, 19)} UTC`;
}

/** The banner to show for a status, or null while the history is stored (or unknown). */
export function bannerFor(history: HistoryStatus | null | undefined): Banner | null {
  if (!history || history.storing) return null;
  const since = history.failing_since_ms ?? history.last_stored_ms;
  const text = since === null ? "history not stored" : `history not stored since ${utcClock(since)}`;
  return {
    text,
    title: `${history.reason ?? "the server refuses to store new events"}. `
      + "Nothing acknowledged is lost: the events wait and are stored once the server recovers.",
  };
}

/** What one poll learnt: the status, or nothing. */
export type Poll = { history: HistoryStatus | null } | "unknown";

/** One GET /api/v1/status through the page's request layer (its session; a busy server
 * waited for): a failure (the server restarting, a 401 the page reports elsewhere) says
 * nothing, and the next poll asks again. */
export async function pollStatus(base = "", opts: FetchOptions = {}): Promise<Poll> {
  try {
    const r = await sharedGet(`${base}/api/v1/status`, undefined, opts);
    if (r.status < 200 || r.status > 299) return "unknown";
    const body = JSON.parse(r.text) as { history?: HistoryStatus | null };
    return { history: body.history ?? null };
  } catch {
    return "unknown";
  }
}
