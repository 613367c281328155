/**
 * The incidents panel's state: the incidents of the timeline's span (read while the panel is
 * open, with its kinds and robot; the area drawn on the map, the change feed's, applied
 * here), what the live stream announces merged in as it comes (a live page asks nothing to
 * see a new one), the picked incident (the map seeks a few seconds before it, rings its
 * robots and draws their trails), and previous/next incident.
 *
 * Reads keep the page's budget (lib/cadence.ts): while live, a list read on the stream's
 * connection is kept current by it (read again on a new connection, as the one before may
 * have missed some); otherwise a span reaching now is read ahead past it, so its end sliding with the
 * clock asks nothing until then, and read again at the page's cadence.
 */
import { computed, ref, shallowRef, watch, type Ref, type ShallowRef } from "vue";
import { getJson } from "../lib/api";
import type { ChunkBox } from "../lib/changefeed";
import { mayGrow, readAheadTo, REFRESH_MS } from "../lib/cadence";
import type { ReplayEngine } from "../lib/engine";
import { applyAnnouncement, incidentSeek, incidentsUrl, isKind, KIND_STYLE, measureText, neighbourIncident, shownIncidents,
  sortByStart, trailWindow, type Incident, type IncidentAnnouncement, type IncidentKind, type IncidentQuery } from "../lib/incidents";
import type { MapView } from "../lib/mapview";
import { oldestReadable } from "../lib/retention";
import { trailRuns, type TrailPoint } from "../lib/trail";
import type { MapMeta } from "../lib/types";
import { formatUtc, type UrlState } from "../lib/urlstate";

export interface IncidentDeps {
  engine: ReplayEngine;
  view: ShallowRef<MapView | null>;
  initial: UrlState;
  /** The timeline's span [from, to). */
  span: () => [number, number];
  /** The area drawn on the map (the change feed's), null: the whole floor. */
  area: Ref<ChunkBox | null>;
  /** The panel is open; `open()` opens it. */
  isOpen: () => boolean;
  open: () => void;
  /** Leaves live mode, pauses and seeks to an instant. */
  pauseAt: (t: number) => void;
  notice: Ref<string | null>;
}

/** The most one read lists (the API's answer says when it cut there). */
export const INCIDENT_LIMIT = 5000;

export function useIncidents(d: IncidentDeps) {
  const { engine, view } = d;
  const kinds = ref<IncidentKind[]>(d.initial.incidentKinds.filter(isKind));
  const robot = ref<string | null>(d.initial.incidentRobot);
  const picked = ref<string | null>(d.initial.incident);
  const items = shallowRef<Incident[]>([]);
  /** Every robot an incident read named (the robot filter offers them: a list filtered by
   * one robot names no other). */
  const robotsSeen = shallowRef<string[]>([]);
  const truncated = ref(false);
  const loading = ref(false);
  const error = ref<string | null>(null);
  const query = (): IncidentQuery => ({ kinds: kinds.value, robot: robot.value });
  const queryKey = () => JSON.stringify(query());

  /** What was read: [from, to) (to past now for a span reaching it), for which query, when,
   * and, if the live stream was connected then, its connection (-1: not live). */
  let read = { from: 0, to: 0, key: "", at: 0, stream: -1 };
  let asked = 0;
  let failedAt = -Infinity;

  /** The map's meta as of the last tick (the engine's is not reactive): the area's chunks. */
  const meta = shallowRef<MapMeta | null>(null);
  const list = computed(() => shownIncidents(items.value, d.span(), d.area.value, meta.value));
  /** Newest first, as the panel lists them. */
  const newestFirst = computed(() => [...list.value].reverse());

  async function load(): Promise<void> {
    const mine = ++asked;
    const now = Date.now();
    const [from, to] = d.span();
    const until = readAheadTo(to, now);
    read = { from, to: until, key: queryKey(), at: now, stream: streamNow() };
    loading.value = true;
    try {
      const page = await getJson<{ incidents: Incident[]; truncated: boolean }>(
        incidentsUrl(engine.api.base, Math.max(from, oldestReadable(now)), until, query(), INCIDENT_LIMIT), "the incidents");
      if (mine !== asked) return;
      items.value = sortByStart(page.incidents);
      const named = new Set([...robotsSeen.value, ...page.incidents.flatMap((i) => i.robots)]);
      if (named.size > robotsSeen.value.length) robotsSeen.value = [...named].sort();
      truncated.value = page.truncated;
      error.value = null;
      afterLoad();
    } catch (e) {
      if (mine === asked) {
        error.value = (e as Error).message;
        failedAt = Date.now();
        read = { ...read, key: "" }; // read again, once a refresh has passed
      }
    } finally {
      if (mine === asked) loading.value = false;
    }
  }

  /** With the summary (a few times a second): reads again what is due, one read at a time. */
  function tick() {
    if (!d.isOpen()) return;
    if (meta.value !== engine.meta) meta.value = engine.meta;
    if (loading.value || Date.now() - failedAt < REFRESH_MS) return;
    const [from, to] = d.span();
    const stream = streamNow();
    if (stream >= 0 && read.key === queryKey() && from >= read.from && !truncated.value) {
      // Live on the connection the list was read on: the stream brings every new incident.
      // On another (the first, or after a drop that may have lost some): read once more.
      if (stream !== read.stream) void load();
      else read.to = Math.max(read.to, readAheadTo(to, Date.now()));
      return;
    }
    const covered = read.key === queryKey() && from >= read.from && to <= read.to && !(truncated.value && from !== read.from);
    const due = stream < 0 && mayGrow(read.to, read.at) && Date.now() - read.at > REFRESH_MS;
    if (!covered || due) void load();
  }

  /** The live stream's connection (its number) while live and connected, else -1:
   * what it announced on one connection, none missed, keeps a list read on it current. */
  function streamNow(): number {
    return engine.clock.live && engine.live.status.connected ? engine.live.status.connections : -1;
  }

  // A filter changed: the list shown is the old one's until the new one is read.
  watch([kinds, robot], () => {
    if (d.isOpen()) void load();
  });
  // Closed, the panel hears no announcement: opened again, it reads its list again.
  watch(d.isOpen, (open) => {
    if (open) return;
    read = { ...read, key: "" };
    items.value = [];
  });

  /** A live announcement: merged into what was read (for the read's window and query). */
  engine.onIncident = (a: IncidentAnnouncement) => {
    if (!d.isOpen() || !read.key) return;
    items.value = applyAnnouncement(items.value, a, read, query());
    if (a.incident.id === picked.value && a.retracted) unpick();
  };

  let trailsFor = "";
  /** The map shows `i` picked: its robots ringed, its place, their trails around it. */
  function showOnMap(i: Incident) {
    const style = KIND_STYLE[i.kind];
    const title = `${style.label}: ${i.robots.join(", ")} · ${formatUtc(i.start_ms)} · ${measureText(i)}`;
    const mark = { robots: i.robots, x: i.x, y: i.y, colour: style.colour, title };
    view.value?.showIncident(mark);
    trailsFor = i.id;
    const [a, b] = trailWindow(i);
    const from = Math.max(a, oldestReadable(Date.now()));
    // A point a second: a trail of a few minutes, drawn as the robots drove it.
    const step = Math.max(1000, Math.round((b - from) / 600));
    void Promise.all(i.robots.map(async (id): Promise<[string, TrailPoint[][]]> => {
      try {
        const points = await engine.api.track(id, from, b, step);
        return [id, trailRuns(points.map((p) => ({ ts_ms: p.ts_ms, x: p.position[0], y: p.position[1] })))];
      } catch {
        return [id, []];
      }
    })).then((trails) => {
      if (trailsFor === i.id) view.value?.showIncident(mark, new Map(trails));
    });
  }

  /** A click on an incident (or its step key): a few seconds before it, its robots shown. */
  function pick(i: Incident) {
    picked.value = i.id;
    d.pauseAt(incidentSeek(i));
    showOnMap(i);
  }

  function unpick() {
    picked.value = null;
    trailsFor = "";
    view.value?.showIncident(null);
  }

  let shownPick = "";
  let pendingStep: 0 | 1 | -1 = 0;
  /** After a read: a pick the address named is shown once its incident is listed. */
  function afterLoad() {
    const i = picked.value ? items.value.find((x) => x.id === picked.value) : undefined;
    if (i && shownPick !== i.id) {
      shownPick = i.id;
      showOnMap(i);
    }
    if (pendingStep) {
      const dir = pendingStep;
      pendingStep = 0;
      step(dir);
    }
  }

  /** [ / ]: the previous/next incident of the panel's list from the playhead (or from the
   * picked one while the playhead is where its pick left it). Closed, the panel opens and
   * steps once it has read its list. */
  function step(dir: 1 | -1) {
    if (!d.isOpen()) {
      pendingStep = dir;
      d.open();
      return;
    }
    const next = neighbourIncident(list.value, picked.value, engine.playhead, dir);
    if (next) pick(next);
    else d.notice.value = `no ${dir > 0 ? "later" : "earlier"} incident in the timeline's span with the panel's filters: zoom out to look further`;
  }

  /** The first listed incident beginning in [from, to) (a click on the timeline's lane). */
  function pickIn(from: number, to: number) {
    const i = list.value.find((x) => x.start_ms >= from && x.start_ms < to) ?? list.value.find((x) => x.end_ms >= from && x.start_ms < to);
    if (i) pick(i);
  }

  /** Once the map is there: the pick the address named, if read already. */
  function attach() {
    shownPick = "";
    afterLoad();
  }

  const state = () => ({ kinds: kinds.value, robot: robot.value, picked: picked.value });

  return { kinds, robot, picked, items, robotsSeen, list, newestFirst, truncated, loading, error, tick, pick, unpick, step, pickIn, attach, state };
}

export type IncidentsState = ReturnType<typeof useIncidents>;
