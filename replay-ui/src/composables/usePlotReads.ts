/**
 * The plot panel's reads: the chosen robots' per-bucket aggregates over the timeline's
 * span (about a bucket every three pixels, the size chosen by the API), read again
 * when the robots change or the span moved by 2 % of its length (a span sliding with
 * playback or live). A failed read is tried again after 1 s, 2 s, 4 s ... at most
 * RETRY_MAX_MS apart, the plots drawn so far kept and the error said (a request the API
 * refuses as such, a 400 or 422, is said and not repeated); a span reaching the
 * present (poses still arriving, a history still being written) is read again every
 * REFRESH_MS, so a read that came back thin or early is not the last one.
 */
import { onScopeDispose, ref, shallowRef, watch } from "vue";
import { ApiError } from "../lib/api";
import { RETENTION_MS } from "../lib/retention";
import { plotBuckets, seriesOf, type RobotSeries } from "../lib/plots";
import type { TrackBuckets } from "../lib/types";

export interface PlotData {
  bucketMs: number;
  from: number;
  to: number;
  series: Map<string, RobotSeries>;
}

/** Waits this long after a change of robots or span (a drag or a scrub makes many). */
export const READ_DELAY_MS = 200;
export const RETRY_FIRST_MS = 1_000;
export const RETRY_MAX_MS = 30_000;
export const REFRESH_MS = 30_000;
/** Answers that a repeat would get again (a bad window, no access): not tried again. */
const REFUSED = new Set([400, 401, 403, 422]);
/** A span ending less than this before the present may still gain poses. */
export const GROWING_MS = 5 * 60_000;
/** The longest window the API reads in one request is the retention. */
const MAX_WINDOW_MS = RETENTION_MS;

export interface PlotReadOptions {
  /** Reads one robot's poses in [from, to) aggregated in at most `buckets` buckets. */
  read: (robotId: string, fromMs: number, toMs: number, buckets: number) => Promise<TrackBuckets>;
  robots: () => string[];
  /** The span to show, [from, to) in ms (props read in a getter). */
  span: () => readonly [number, number];
  /**
   * The oldest instant the API reads, asked at each read (the page's one definition of
   * the retention clamp): a span starting before it is read from it.
   */
  oldestMs: () => number;
  /** The plotting width in px (the number of buckets follows from it). */
  width: () => number;
  /** New data to draw. */
  drawn?: () => void;
  /** The span moved too little to read again: only the axis moves. */
  rescaled?: () => void;
}

export function usePlotReads(o: PlotReadOptions) {
  const data = shallowRef<PlotData>({ bucketMs: 0, from: 0, to: 0, series: new Map() });
  const loading = ref(false);
  const error = ref<string | null>(null);
  let timer: ReturnType<typeof setTimeout> | null = null;
  let loadedKey = "";
  let asked: { robots: string; from: number; to: number } | null = null;
  let failures = 0;
  let disposed = false;

  function later(ms: number) {
    if (timer) clearTimeout(timer);
    timer = disposed ? null : setTimeout(() => void load(), ms);
  }

  function schedule() {
    // A span sliding along with playback reloads once it moved 2 % of its length.
    const [fromMs, toMs] = o.span();
    const slack = (toMs - fromMs) / 50;
    // Compared with the last read asked, not the last answered: a read under way is of it.
    const a = asked;
    const same = a !== null && o.robots().join() === a.robots && Math.abs(a.from - fromMs) < slack
      && Math.abs(a.to - toMs) < slack;
    if (same) o.rescaled?.();
    else later(READ_DELAY_MS);
  }

  async function load() {
    timer = null;
    const [spanFrom, toMs] = o.span();
    const to = Math.round(toMs);
    // The API reads nothing older than the oldest instant, in one window of at most the
    // retention (a span ending in the future may be longer than what is kept before now).
    const from = Math.round(Math.max(spanFrom, o.oldestMs(), to + 1 - MAX_WINDOW_MS));
    const buckets = plotBuckets(o.width());
    const ids = [...o.robots()];
    const key = `${ids.join()}|${from}|${to}`;
    loadedKey = key;
    asked = { robots: ids.join(), from, to };
    loading.value = true;
    try {
      const answers = await Promise.all(ids.map((id) => o.read(id, from, to + 1, buckets)));
      if (loadedKey !== key || disposed) return;
      const bucketMs = answers[0]?.bucket_ms ?? 0;
      data.value = { bucketMs, from, to, series: new Map(ids.map((id, i) => [id, seriesOf(answers[i])])) };
      error.value = null;
      failures = 0;
      o.drawn?.();
      if (ids.length && Date.now() - to < GROWING_MS) later(REFRESH_MS);
    } catch (e) {
      if (loadedKey !== key || disposed) return;
      const why = e instanceof Error ? e.message : String(e);
      // Refused again if repeated: said, not repeated (a change of span or robots reads).
      if (e instanceof ApiError && REFUSED.has(e.status)) {
        error.value = `plots not read (${why.slice(0, 160)})`;
        return;
      }
      const wait = Math.min(RETRY_MAX_MS, RETRY_FIRST_MS * 2 ** failures++);
      error.value = `plots not read (${why.slice(0, 100)}): trying again in ${Math.round(wait / 1000)} s`;
      later(wait);
    } finally {
      if (loadedKey === key) loading.value = false;
    }
  }

  watch(() => [o.robots().join(), ...o.span()], schedule);
  onScopeDispose(() => {
    disposed = true;
    if (timer) clearTimeout(timer);
  });

  return { data, loading, error, load };
}
