/**
 * A list read for the timeline's span, page by page (the change feed, the conflict
 * inspector): refetched when the span moved by 2 % of its length or more, or when a filter
 * changed, at most every 300 ms while the span slides with playback; loading and error
 * state; an answer to an older request never overwrites a newer one.
 */
import { onScopeDispose, ref, shallowRef, watch, type Ref } from "vue";

/** One page as the panel's read gives it: its entries, the cursor of the next (older) page
 * (null: the last), and what else the answer said (rules, truncation). */
export interface SpanPage<T, M> {
  items: T[];
  next: string | null;
  info: M;
}

export interface SpanListOptions<T, M> {
  /** The span to list, [from, to) in ms (reactive: props read in a getter). */
  span: () => readonly [number, number];
  /** The filters as one string: a change reloads whatever the span did. */
  filterKey?: () => string;
  /** Reads the page of [from, to) after `cursor` (null: the first). */
  fetchPage: (fromMs: number, toMs: number, cursor: string | null) => Promise<SpanPage<T, M>>;
  /** Say "loading" as soon as a reload is due, not only once it is asked (a filter's
   * change: the list shown is the old filter's until the new one is read). */
  loadingAtOnce?: boolean;
}

export const RELOAD_DELAY_MS = 300;
/** A span that moved less than this share of its length is not read again. */
export const RELOAD_SHARE = 1 / 50;

export function useSpanList<T, M>(opts: SpanListOptions<T, M>) {
  const items = shallowRef<T[]>([]) as Ref<T[]>;
  const next = ref<string | null>(null);
  const info = shallowRef<M | null>(null) as Ref<M | null>;
  const error = ref<string | null>(null);
  const loading = ref(true);
  let asked = 0;

  /** Reads the first page of the span (or, with `more`, the page after the last one read). */
  async function load(more = false) {
    const mine = ++asked;
    loading.value = true;
    const [from, to] = opts.span();
    try {
      const page = await opts.fetchPage(from, to, more ? next.value : null);
      if (mine !== asked) return;
      items.value = more ? [...items.value, ...page.items] : page.items;
      next.value = page.next;
      info.value = page.info;
      error.value = null;
    } catch (e) {
      if (mine === asked) error.value = String(e instanceof Error ? e.message : e);
    } finally {
      if (mine === asked) loading.value = false;
    }
  }

  let timer: ReturnType<typeof setTimeout> | null = null;
  let loadedFor = { from: 0, to: 0, key: "" };
  watch(() => [...opts.span(), opts.filterKey?.() ?? ""] as const, ([f, t, key]) => {
    const slack = (t - f) * RELOAD_SHARE;
    if (key === loadedFor.key && Math.abs(f - loadedFor.from) < slack && Math.abs(t - loadedFor.to) < slack) return;
    loadedFor = { from: f, to: t, key };
    if (opts.loadingAtOnce) loading.value = true;
    if (timer) clearTimeout(timer);
    timer = setTimeout(() => void load(), RELOAD_DELAY_MS);
  }, { immediate: true });
  onScopeDispose(() => {
    if (timer) clearTimeout(timer);
  });

  return { items, next, info, error, loading, load };
}
