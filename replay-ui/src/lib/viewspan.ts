/**
 * The timeline's view (the span it shows, which the change feed lists, the plots show and
 * the address keeps) and the playhead: one rule keeps the playhead in view.
 *
 * - When the playhead moves (playing, live, a seek, a step, a pick in a list), the view
 *   follows it: a playhead leaving the view slides the view along, its length kept.
 * - When the view moves (a drag, the wheel, a preset, −, ⟲ back, a typed span), the
 *   playhead follows the view: it stays where it is if the new view holds it, else it goes
 *   to the nearest instant the view holds. In live mode that leaves live: the page pauses
 *   at the view's end. (Before, a view dragged into the past snapped back to now, and a
 *   zoom left the map at an instant the timeline no longer showed.)
 *
 * Presets: live, the last N (ending now); otherwise N centred on the playhead. Every span
 * is within the history kept and now, at least a second long, on whole milliseconds (the
 * address keeps milliseconds: a link reopens exactly the span that was seen).
 *
 * Pure: now and the oldest instant kept are passed in.
 */
import { fromInputValue, PICKER_FORMATS } from "./urlstate";

export const MIN_SPAN_MS = 1000;
export const DEFAULT_SPAN_MS = 3_600_000;

export type Span = [number, number];

/** Where a span may lie: [minMs, now] (the oldest instant the history keeps, and now). */
export interface Bounds {
  minMs: number;
  now: number;
}

/**
 * [a, b) moved (not cut) to lie within the bounds, on whole milliseconds: a zoom near an
 * end keeps the length asked for; only a span longer than the history kept is cut to it.
 */
export function fitSpan(a: number, b: number, bounds: Bounds): Span {
  const room = Math.max(MIN_SPAN_MS, Math.floor(bounds.now - bounds.minMs));
  const len = Math.min(room, Math.max(MIN_SPAN_MS, Math.round(b - a)));
  let from = Math.round(a);
  if (from + len > bounds.now) from = Math.floor(bounds.now) - len;
  if (from < bounds.minMs) from = Math.ceil(bounds.minMs);
  return [from, from + len];
}

/** The nearest instant the view holds (the playhead itself when the view holds it). */
export function clampToView(t: number, [from, to]: Span): number {
  return Math.min(to, Math.max(from, t));
}

export function holds([from, to]: Span, t: number): boolean {
  return t >= from && t <= to;
}

/** A preset of `len`: live, the last `len`; otherwise `len` centred on the playhead. */
export function presetSpan(len: number, playhead: number, live: boolean, bounds: Bounds): Span {
  return live ? fitSpan(bounds.now - len, bounds.now, bounds) : fitSpan(playhead - len / 2, playhead + len / 2, bounds);
}

/** Twice the span, around its middle. */
export function widerSpan([from, to]: Span, bounds: Bounds): Span {
  const mid = (from + to) / 2;
  return fitSpan(mid - (to - from), mid + (to - from), bounds);
}

/** The wheel: `factor` times the span, the instant `t` under the pointer staying put. */
export function wheelSpan([from, to]: Span, t: number, factor: number, bounds: Bounds): Span {
  return fitSpan(t - (t - from) * factor, t + (to - t) * factor, bounds);
}

/**
 * The view once the playhead moved to `t`: unchanged while it holds `t`; else slid (its
 * length kept) so that `t` is in it: forwards past the end (playing, live) the playhead
 * ends up mid-span, or at the end near now; backwards before the start, mid-span.
 */
export function followPlayhead(view: Span, t: number, bounds: Bounds): Span {
  const [from, to] = view;
  const len = to - from;
  if (t > to) {
    const end = Math.max(t, Math.min(bounds.now, Math.round(t + len / 2)));
    return [end - len, end];
  }
  if (t < from) {
    const start = Math.min(t, Math.max(Math.ceil(bounds.minMs), Math.round(t - len / 2)));
    return [start, start + len];
  }
  return view;
}

/**
 * What a move of the view does to the playhead: null, nothing (the view holds it: live
 * stays live); else where it goes, the nearest instant in view (a seek there leaves live).
 */
export function playheadAfterViewMove(view: Span, playhead: number): number | null {
  return holds(view, playhead) ? null : clampToView(playhead, view);
}

/**
 * The span the page opens on, from its address: the address's span, if any (a link made
 * live keeps its length and ends now, as the live view slid on); else an hour, ending now
 * when live, else centred on the address's instant. An address whose instant is outside
 * its span (made by hand) gets the view moved to the instant, as a seek would.
 */
export function openingSpan(address: { span: Span | null; live: boolean; t: number | null }, bounds: Bounds): Span {
  const live = address.live || address.t === null;
  const t = live ? bounds.now : Math.min(bounds.now, Math.max(bounds.minMs, address.t!));
  if (!address.span) return presetSpan(DEFAULT_SPAN_MS, t, live, bounds);
  const len = address.span[1] - address.span[0];
  if (live) return fitSpan(bounds.now - len, bounds.now, bounds);
  return followPlayhead(fitSpan(address.span[0], address.span[1], bounds), t, bounds);
}

export type TypedSpan = { span: Span; note: string | null } | { error: string };

/**
 * A span typed as two instants (the time box's formats, UTC): the span, with a note when
 * it was cut to the history kept or to now; or what is wrong with it.
 */
export function typedSpan(fromText: string, toText: string, bounds: Bounds): TypedSpan {
  const from = fromInputValue(fromText);
  const to = fromInputValue(toText);
  const unreadable = (which: string, text: string) =>
    ({ error: `the span's ${which} "${text.trim()}" is not a time: write ${PICKER_FORMATS}` });
  if (from === null) return unreadable("start", fromText);
  if (to === null) return unreadable("end", toText);
  if (to <= from) return { error: "the span's end must be after its start" };
  if (to - from < MIN_SPAN_MS) return { error: "a span is at least a second long" };
  if (to <= bounds.minMs) return { error: "the whole span is older than the history keeps (7 days)" };
  if (from >= bounds.now) return { error: "the whole span is in the future" };
  const cut: string[] = [];
  if (from < bounds.minMs) cut.push("starts at the oldest instant kept");
  if (to > bounds.now) cut.push("ends now");
  const span: Span = [Math.max(from, Math.ceil(bounds.minMs)), Math.min(to, Math.floor(bounds.now))];
  return { span: span[1] - span[0] >= MIN_SPAN_MS ? span : fitSpan(span[0], span[0] + MIN_SPAN_MS, bounds),
    note: cut.length ? `the span ${cut.join(" and ")}` : null };
}
