/**
 * How often the page reads again what the live stream (poses and map writes) does not
 * carry: the commands, the zone edits and violations of a span that reaches now, and the
 * service's status. One cadence for all of them, so that a live page at rest asks the
 * server a few times in REFRESH_MS, not once per list per tick; a span that reaches now is
 * read ahead past it (readAheadTo), so that its end sliding with the clock asks nothing
 * until the next refresh. What the page itself changes (an edit, a command) it shows at
 * once, without waiting for a refresh.
 */
export const REFRESH_MS = 15_000;

/** The end to read a span [.., to) up to: past now by two refreshes when it reaches
 * (almost) now, else its own end. */
export function readAheadTo(to: number, now: number): number {
  return to >= now - REFRESH_MS ? Math.max(to, now + 2 * REFRESH_MS) : to;
}

/** Whether a span read at `readAt` up to `readTo` may have gained entries since: it reached
 * within a refresh of the time it was read (entries are stamped when they happen and stored
 * a moment later); one that ended earlier is history and never changes. */
export function mayGrow(readTo: number, readAt: number): boolean {
  return readTo > readAt - REFRESH_MS;
}

/** A read made at `at` for the instant `t`, reaching up to `until` (readAheadTo). */
export interface SpanRead {
  t: number;
  until: number;
  at: number;
}

/** Whether `read` still answers for the instant `t` at `now`: `t` within `slackMs` of the
 * instant read, or within what was read ahead of it while that may not have grown yet
 * (a live playhead asks again once a refresh, not every `slackMs`). */
export function stillAnswers(read: SpanRead, t: number, now: number, slackMs: number): boolean {
  if (Math.abs(t - read.t) <= slackMs) return true;
  return t >= read.t && t < read.until && !(mayGrow(read.until, read.at) && now - read.at > REFRESH_MS);
}
