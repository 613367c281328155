/**
 * The heatmap layer's state: which heatmap is shown (kind and cell size, or none; the address
 * keeps it), its read for the timeline's span (one PNG for the map, its header the
 * summary for the legend and the box), and the legend's scale bar. A span sliding with
 * playback is read again once it moved by 2 % of its length, at most every 300 ms; a newer
 * read cancels the one before. The page's frame loop rests when nothing moves: the picture
 * is laid on the map when read (or once the map knows its floor), the scale on each zoom.
 */
import { computed, ref, shallowRef, watch, type ShallowRef } from "vue";
import { DEFAULT_CELL_M, heatmapUrl, scaleBar, summaryOf, type HeatmapState, type HeatmapSummary } from "../lib/heatmap";
import type { MapView } from "../lib/mapview";
import { ApiError, Superseding, errorText, getBlobAnswer } from "../lib/request";
import type { UrlState } from "../lib/urlstate";

export interface HeatmapDeps {
  base: string;
  view: ShallowRef<MapView | null>;
  initial: UrlState;
  /** The timeline's span [from, to). */
  span: () => [number, number];
}

/** A span that moved less than this share of its length is not read again. */
const MOVE_SHARE = 0.02;
const SETTLE_MS = 300;
const RETRY_MS = 200;

export function useHeatmap(d: HeatmapDeps) {
  /** Shown: its kind and cell; the controls keep both while it is off. */
  const on = ref(d.initial.heatmap !== null);
  const choice = ref<HeatmapState>(d.initial.heatmap ?? { kind: "occupancy", cell: DEFAULT_CELL_M });
  const state = computed<HeatmapState | null>(() => (on.value ? { ...choice.value } : null));
  const grid = shallowRef<HeatmapSummary | null>(null);
  const loading = ref(false);
  const error = ref<string | null>(null);
  const metresPerPx = ref(0);
  const bar = computed(() => (metresPerPx.value > 0 ? scaleBar(metresPerPx.value) : null));
  const reads = new Superseding();
  let picture: string | null = null; // the object URL of the PNG shown
  let retry: ReturnType<typeof setTimeout> | null = null;
  let read: { key: string; from: number; to: number } | null = null;
  let timer: ReturnType<typeof setTimeout> | null = null;

  /** Lays the grid read last on the map; until the map knows its floor, tries again. */
  function draw() {
    const g = grid.value;
    const v = d.view.value;
    if (retry) clearTimeout(retry);
    retry = null;
    if (!v) {
      retry = setTimeout(draw, RETRY_MS);
      return;
    }
    const box = g?.box ? {
      x0: g.box.i0 * g.cell_m, y0: g.box.j0 * g.cell_m,
      x1: (g.box.i0 + g.box.columns) * g.cell_m, y1: (g.box.j0 + g.box.rows) * g.cell_m,
    } : null;
    if (!v.showHeatmap(on.value && box ? picture : null, box)) retry = setTimeout(draw, RETRY_MS);
  }

  async function load(s: HeatmapState, span: [number, number]) {
    const signal = reads.next();
    loading.value = true;
    try {
      const now = Date.now();
      const answer = await getBlobAnswer(heatmapUrl(d.base, s, span, now, "png"), "the heatmap", signal);
      const g = summaryOf(answer.headers);
      if (picture) URL.revokeObjectURL(picture);
      picture = g.box ? URL.createObjectURL(answer.blob) : null;
      grid.value = g;
      error.value = null;
      draw();
    } catch (e) {
      // A refused heatmap says what to change (a larger cell, a shorter span): show it.
      if (!signal.aborted) error.value = e instanceof ApiError && e.detail ? `${e.message} (${e.detail})` : errorText(e);
    } finally {
      if (!signal.aborted) loading.value = false;
    }
  }

  function schedule() {
    const s = state.value;
    if (!s) {
      reads.cancel();
      if (retry) clearTimeout(retry);
      retry = null;
      read = null;
      loading.value = false;
      d.view.value?.showHeatmap(null, null);
      return;
    }
    const [from, to] = d.span();
    const key = JSON.stringify(s);
    const slack = (to - from) * MOVE_SHARE;
    if (read && read.key === key && Math.abs(read.from - from) < slack && Math.abs(read.to - to) < slack) return;
    if (timer) clearTimeout(timer);
    timer = setTimeout(() => {
      timer = null;
      read = { key, from, to };
      void load(s, [from, to]);
    }, read?.key === key ? SETTLE_MS : 0);
  }

  watch(() => [state.value, ...d.span()], schedule, { immediate: true });

  // The scale bar follows the view's zoom.
  const rescale = () => (metresPerPx.value = d.view.value?.metresPerScreenPixel() ?? 0);
  watch(d.view, (v) => {
    v?.map.on("zoomend", rescale);
    rescale();
  }, { immediate: true });

  return { on, choice, state, grid, loading, error, bar };
}
