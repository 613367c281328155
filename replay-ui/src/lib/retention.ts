/** How far back the history keeps events (the service's seven-day TTL). */
export const RETENTION_MS = 7 * 86_400_000;

/**
 * The oldest instant the history keeps at `nowMs`, with a minute's margin: it moves on
 * while a request is under way, and the API refuses a window that starts before it.
 */
export function oldestReadable(nowMs: number, retentionMs: number = RETENTION_MS): number {
  return nowMs - retentionMs + 60_000;
}
