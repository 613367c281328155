/**
 * The page's annotations: the points of interest and zones standing at the playhead (read
 * again whenever the playhead crosses one of their edits), the edits and zone violations of
 * the timeline's span (its marks, the panel's list), and an operator's edits (drawn on the
 * map, sent to the API, every refusal shown with the server's message).
 *
 * An edit happens now (the server stamps it). The playhead stays where the operator is
 * looking (a replay paused in the past is not moved to now): the status names the edit's
 * instant and offers to go there, where the map shows its result.
 */
import { computed, onBeforeUnmount, onMounted, reactive, ref, shallowRef, type ShallowRef } from "vue";
import { AnnotationApi } from "../lib/annotationapi";
import {
  closeRing, crossesEdit, movedZone, sameEdit, timelineMarks, unreflectedEdits, violationEpisodes, violationsAt,
  type Annotation, type AnnotationDoc, type AnnotationEdit, type Point, type PoiKind, type ZoneDoc, type ZoneKind, type ZoneViolation,
} from "../lib/annotations";
import { setApiToken } from "../lib/auth";
import { resolutionOf } from "../lib/geo";
import { mayGrow, readAheadTo, REFRESH_MS } from "../lib/cadence";
import type { MapView } from "../lib/mapview";

export interface AnnotationDeps {
  base: string;
  view: ShallowRef<MapView | null>;
  /** The timeline's span [from, to): its edits and violations are read for the marks and list. */
  span: () => [number, number];
  seek: (t: number) => void;
  live: () => boolean;
}

/** How long a violation stays marked on the map after the pose that made it. */
export const VIOLATION_SHOWN_MS = 30_000;

/** How long this page's own edit is kept while the store's edits do not hold it yet. */
const PENDING_MS = 120_000;

/** How often the annotations at the playhead are read again while they lack this page's edit. */
const LAGGING_READ_MS = 500;

export function useAnnotations(d: AnnotationDeps) {
  const api = new AnnotationApi(d.base);
  const list = shallowRef<Annotation[]>([]);
  const edits = shallowRef<AnnotationEdit[]>([]);
  const violations = shallowRef<ZoneViolation[]>([]);
  const truncated = ref(false);
  const episodes = computed(() => violationEpisodes(violations.value));
  const marks = computed(() => timelineMarks(edits.value, episodes.value));
  const operator = ref(false);
  const selected = ref<string | null>(null);
  const tool = ref<"zone" | "poi" | null>(null);
  const error = ref<string | null>(null);
  const status = ref<string | null>(null);
  const busy = ref(false);
  /** The instant of this page's last stored edit (null: none yet), for "show it". */
  const editedAt = ref<number | null>(null);
  const form = reactive({
    zoneName: "keep-out", zoneKind: "keep_out" as ZoneKind, speed: 0.5, speedUnit: "m/s" as "m/s" | "percent",
    poiName: "", poiKind: "station" as PoiKind, rename: "",
  });
  /** The instant `list` was read for (NaN: not yet), and the span the edits were read for. */
  let loadedAt = NaN;
  let listLoading = false;
  let dirty = false;
  /** The span the edits and violations were read for, up to where (past a live span's
   * end) and when. */
  let win = { from: 0, to: 0, until: 0, at: 0 };
  let winLoading = false;
  let drawnKey = "";
  /** This page's own edits, until the store's edits hold them (a second or two): the
   * playhead crossing one must read the annotations again before the store has it. */
  let pending: AnnotationEdit[] = [];
  /** When `list` was read without one of this page's edits at or before its instant (0:
   * it shows them all): read again every LAGGING_READ_MS until the store holds them. */
  let laggingSince = 0;

  async function loadList(t: number) {
    listLoading = true;
    dirty = false;
    try {
      list.value = await api.at(t);
      loadedAt = t;
      const recent = pending.filter((p) => Date.now() - p.ts_ms < PENDING_MS);
      laggingSince = unreflectedEdits(recent, list.value, t).length ? Date.now() : 0;
    } catch (e) {
      error.value = `annotations at the playhead could not be read: ${(e as Error).message}`;
      loadedAt = t; // not again every frame: the next edit crossed or seek asks again
    } finally {
      listLoading = false;
    }
  }

  async function loadWindow(from: number, to: number) {
    winLoading = true;
    const now = Date.now();
    // A span reaching now is read ahead past it: its end sliding with the clock reads
    // nothing new until the next refresh.
    const until = readAheadTo(to, now);
    win = { from, to, until, at: now };
    try {
      const [e, v] = await Promise.all([api.edits(from, until), api.violations(from, until)]);
      pending = pending.filter((p) => Date.now() - p.ts_ms < PENDING_MS && !e.items.some((x) => sameEdit(x, p)));
      edits.value = [...e.items, ...pending];
      violations.value = v.items;
      truncated.value = v.truncated;
    } catch {
      // A span beyond the retention (or a failed read): no marks.
      edits.value = [];
      violations.value = [];
    } finally {
      winLoading = false;
    }
  }

  /** Called a few times a second with the playhead: reads what changed, redraws what moved. */
  function tick(t: number) {
    const [from, to] = d.span();
    const slack = (to - from) / 50;
    // A span reaching now gains edits and violations as they are stored: read again every
    // refresh; its end sliding within what was read ahead asks nothing.
    const stale = mayGrow(win.until, win.at) && Date.now() - win.at > REFRESH_MS;
    const moved = Math.abs(from - win.from) > slack || Math.abs(to - win.to) > slack || to > win.until;
    if (!winLoading && (moved || stale)) void loadWindow(from, to);
    // Outside the span the edits were read for, an edit may be unknown: read again every 10 s of playhead.
    const unknown = !(t >= win.from && t < win.until && loadedAt >= win.from && loadedAt < win.until);
    const lagging = laggingSince > 0 && Date.now() - laggingSince > LAGGING_READ_MS;
    if (!listLoading && (dirty || lagging || Number.isNaN(loadedAt) || crossesEdit(edits.value, loadedAt, t)
        || (unknown && Math.abs(t - loadedAt) > 10_000))) void loadList(t);
    redraw(t);
  }

  function redraw(t: number, force = false) {
    const layer = d.view.value?.annotations;
    if (!layer) return;
    const shown = violationsAt(violations.value, t, VIOLATION_SHOWN_MS);
    const key = JSON.stringify([list.value.map((a) => [a.id, a.changed_ms]), selected.value, operator.value,
      shown.map((v) => [v.robotId, v.ts_ms]), d.view.value?.meta?.resolution]);
    if (key === drawnKey && !force) return;
    drawnKey = key;
    layer.on = { select, movePoint, moveZone };
    layer.draw(list.value, selected.value, operator.value);
    layer.drawViolations(shown);
  }

  function find(id: string | null): Annotation | undefined {
    return list.value.find((a) => a.id === id);
  }

  function select(id: string | null) {
    selected.value = id;
    form.rename = find(id)?.annotation.name ?? "";
    drawnKey = "";
  }

  /** Sends an edit; on success reads again and shows where it stands, else shows why not. */
  async function edit(what: string, kind: AnnotationEdit["change"], send: () => Promise<Annotation | null>) {
    busy.value = true;
    error.value = null;
    status.value = null;
    try {
      const r = await send();
      const at = r ? r.changed_ms : Date.now();
      // Known at once (the store has it a second later): the playhead crossing it reads again.
      const mine: AnnotationEdit = { ts_ms: at, event_id: `local:${at}:${what}`, id: r?.id ?? selected.value ?? "",
        change: kind, by: "you", annotation: r?.annotation ?? null };
      pending.push(mine);
      edits.value = [...edits.value, mine];
      status.value = `${what}: stored at ${new Date(at).toISOString().replace("T", " ").slice(0, 19)} UTC`;
      if (r) select(r.id);
      dirty = true;
      win.at = 0;
      editedAt.value = at;
    } catch (e) {
      error.value = `${what} refused: ${(e as Error).message}`;
    } finally {
      busy.value = false;
      drawnKey = "";
    }
  }

  function drawZone() {
    const layer = d.view.value?.annotations;
    const meta = d.view.value?.meta;
    if (!layer || !meta) return;
    tool.value = "zone";
    error.value = null;
    layer.startPolygon((vertices: Point[]) => {
      tool.value = null;
      const ring = closeRing(vertices, resolutionOf(meta));
      if (!ring) {
        error.value = "a zone needs three corners or more, not in one line: click them on the map, then double-click or press Enter";
        return;
      }
      const zone: ZoneDoc = { shape: "zone", name: form.zoneName.trim(), kind: form.zoneKind, polygon: ring };
      if (form.zoneKind === "speed_limit") Object.assign(zone, { speed_limit: form.speed, speed_unit: form.speedUnit });
      void edit(`zone ${zone.name}`, "created", () => api.create(zone));
    });
  }

  function placePoi() {
    const layer = d.view.value?.annotations;
    if (!layer) return;
    tool.value = "poi";
    error.value = null;
    layer.placePoint((x, y) => {
      tool.value = null;
      const name = form.poiName.trim();
      void edit(`point ${name}`, "created", () => api.create({ shape: "poi", name, kind: form.poiKind, x, y }));
    });
  }

  function cancelTool() {
    d.view.value?.annotations.cancel();
    tool.value = null;
  }

  function change(id: string, what: string, doc: AnnotationDoc) {
    void edit(what, "changed", () => api.change(id, doc));
  }

  function movePoint(id: string, x: number, y: number) {
    const a = find(id);
    if (a?.annotation.shape === "poi") change(id, `move ${a.annotation.name}`, { ...a.annotation, x, y });
  }

  function moveZone(id: string, dx: number, dy: number) {
    const a = find(id);
    if (a?.annotation.shape === "zone") change(id, `move ${a.annotation.name}`, movedZone(a.annotation, dx, dy));
  }

  function rename() {
    const a = find(selected.value);
    if (a) change(a.id, `rename ${a.annotation.name}`, { ...a.annotation, name: form.rename.trim() });
  }

  function remove() {
    const a = find(selected.value);
    if (!a) return;
    void edit(`remove ${a.annotation.name}`, "removed", async () => {
      await api.remove(a.id);
      return null;
    }).then(() => {
      if (!error.value) select(null);
    });
  }

  async function checkAccess() {
    operator.value = (await api.scopes()).includes("operator");
    drawnKey = "";
  }

  function useToken(token: string) {
    setApiToken(token);
    void checkAccess();
  }

  /** Enter closes the polygon being drawn, Esc drops it (before the page's own keys: Esc there unselects). */
  function onKey(e: KeyboardEvent) {
    if (!tool.value) return;
    const tag = (e.target as HTMLElement | null)?.tagName;
    if (tag === "INPUT" || tag === "SELECT" || tag === "TEXTAREA") return;
    if (e.key === "Escape") cancelTool();
    else if (e.key === "Enter" && tool.value === "zone") d.view.value?.annotations.finish();
    else return;
    e.preventDefault();
    e.stopImmediatePropagation();
  }
  onMounted(() => {
    window.addEventListener("keydown", onKey, true);
    void checkAccess();
  });
  onBeforeUnmount(() => window.removeEventListener("keydown", onKey, true));

  /** What the browser tests read (window.__replay.annotations()). */
  function hook() {
    const layer = d.view.value?.annotations;
    return { loadedAt, settled: laggingSince === 0, ids: list.value.map((a) => a.id), drawn: layer?.drawn ?? null, tool: layer?.active ?? null,
      vertices: layer?.vertices ?? 0, operator: operator.value,
      shown: !!layer && !!d.view.value?.map.hasLayer(layer.group), marks: marks.value.map((m) => [m.kind, m.ts_ms]) };
  }

  return reactive({
    list, edits, violations, truncated, episodes, marks, operator, selected, tool, error, status, busy, form, editedAt,
    tick, select, drawZone, placePoi, cancelTool, rename, remove, useToken, seek: d.seek, live: d.live, hook,
  });
}

export type AnnotationsState = ReturnType<typeof useAnnotations>;
