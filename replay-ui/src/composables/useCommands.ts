/**
 * The page's commands: every command of the timeline's span (its marks, for everyone), the
 * selected robot's commands with their answers (polled every second while one awaits its
 * ack or outcome, for the state of what an operator sent and the "paused" badge at the
 * playhead), and an operator's commands to the selected robot (every refusal shown with
 * the server's message). Going to a point of interest offers the points standing now.
 */
import { computed, reactive, ref, shallowRef, watch, type Ref } from "vue";
import { AnnotationApi } from "../lib/annotationapi";
import { CommandApi } from "../lib/commandapi";
import { awaiting, commandMarks, mergeCommands, pausedAt, type Command, type CommandKind } from "../lib/commands";
import { oldestReadable } from "../lib/retention";
import { mayGrow, readAheadTo, REFRESH_MS } from "../lib/cadence";

export interface CommandDeps {
  base: string;
  selected: Ref<string | null>;
  operator: () => boolean;
  /** The timeline's span [from, to): its commands are its marks. */
  span: () => [number, number];
}

/** How far before the playhead the selected robot's commands are read (its latest pause). */
const ROBOT_LOOKBACK_MS = 86_400_000;
const POLL_MS = 1_000;
const POIS_EVERY_MS = 2 * REFRESH_MS;
/** The API's default cap on a window's commands (GET /api/v1/commands `limit`). */
const SPAN_LIMIT = 1_000;

export function useCommands(d: CommandDeps) {
  const api = new CommandApi(d.base);
  const annotations = new AnnotationApi(d.base);
  const spanCommands = shallowRef<Command[]>([]);
  const robotCommands = shallowRef<Command[]>([]);
  const pois = shallowRef<{ id: string; name: string }[]>([]);
  const playhead = ref(0);
  const error = ref<string | null>(null);
  const busy = ref(false);
  /** The points of interest's names, for the texts (those standing now, as the select offers them). */
  const names = computed(() => new Map(pois.value.map((p) => [p.id, p.name])));
  const marks = computed(() => commandMarks(mergeCommands(spanCommands.value, robotCommands.value)
    .filter((c) => c.issued_ms >= d.span()[0] && c.issued_ms < d.span()[1]), names.value));
  const paused = computed(() => !!d.selected.value && pausedAt(robotCommands.value, d.selected.value, playhead.value));
  /** The selected robot's latest commands, newest first. */
  const recent = computed(() => [...robotCommands.value].reverse().slice(0, 5));

  /** The last span read: [from, to) as read (past a live span's end), the span asked for,
   * when, and whether the answer was whole (not cut at the limit). */
  let spanRead = { from: 0, to: 0, asked: 0, at: 0, whole: false };
  let robotRead = { id: "", at: 0, around: 0 };
  let poisAt = 0;
  let loading = false;
  /** The commands this page sent to the selected robot and no read has listed yet: the API
   * answers a send once Kafka holds it and the history stores it a moment later, so a read
   * begun before the send, or soon after it, answers without it. Each stays beside the
   * reads' answers until one lists it. */
  let sent: Command[] = [];

  /** Reads the span's commands; a span that ends near now (live: its end slides with the
   * clock) is read ahead to the next refreshes, so that sliding asks nothing until then. */
  async function loadSpan(from: number, to: number, now: number) {
    const until = readAheadTo(to, now);
    spanRead = { from, to: until, asked: to, at: now, whole: true };
    try {
      const got = await api.list(Math.max(from, oldestReadable(now)), until);
      // A window cut at the API's limit covers only itself: a zoom into it reads again.
      spanRead.whole = got.length < SPAN_LIMIT;
      spanCommands.value = got;
    } catch {
      spanCommands.value = [];
    }
  }

  /** Whether the last span read holds every command of [from, to) as of its refresh. */
  function spanCovered(from: number, to: number): boolean {
    if (from === spanRead.from && to === spanRead.asked) return true;
    return spanRead.whole && from >= spanRead.from && to <= spanRead.to;
  }

  async function loadRobot(id: string, around: number) {
    robotRead = { id, at: Date.now(), around };
    const from = Math.max(oldestReadable(Date.now()), Math.min(around, Date.now()) - ROBOT_LOOKBACK_MS);
    try {
      const got = await api.list(from, Date.now() + 60_000, id);
      if (d.selected.value === id) {
        const listed = new Set(got.map((c) => c.commandId));
        sent = sent.filter((c) => !listed.has(c.commandId));
        robotCommands.value = mergeCommands(sent, got);
      }
    } catch (e) {
      error.value = `the robot's commands could not be read: ${(e as Error).message}`;
    }
  }

  async function loadPois() {
    poisAt = Date.now();
    try {
      pois.value = (await annotations.at(Date.now())).filter((a) => a.annotation.shape === "poi")
        .map((a) => ({ id: a.id, name: a.annotation.name }));
    } catch {
      pois.value = [];
    }
  }

  watch(d.selected, () => {
    robotCommands.value = [];
    sent = [];
    error.value = null;
    robotRead = { id: "", at: 0, around: 0 };
  });

  /** A few times a second: reads again what is due (one request at a time). */
  function tick(t: number) {
    playhead.value = t;
    if (loading) return;
    const now = Date.now();
    const [from, to] = d.span();
    const id = d.selected.value;
    const jobs: Promise<void>[] = [];
    const due = mayGrow(spanRead.to, spanRead.at) && now - spanRead.at > REFRESH_MS;
    if (!spanCovered(from, to) || due) jobs.push(loadSpan(from, to, now));
    if (id) {
      const every = robotCommands.value.some(awaiting) ? POLL_MS : REFRESH_MS;
      if (id !== robotRead.id || now - robotRead.at > every || Math.abs(t - robotRead.around) > ROBOT_LOOKBACK_MS / 2) jobs.push(loadRobot(id, t));
      if (d.operator() && now - poisAt > POIS_EVERY_MS) jobs.push(loadPois());
    }
    if (!jobs.length) return;
    loading = true;
    void Promise.all(jobs).finally(() => (loading = false));
  }

  async function send(kind: CommandKind, poiId?: string) {
    const id = d.selected.value;
    if (!id) return;
    busy.value = true;
    error.value = null;
    try {
      const c = await api.send(id, kind, poiId);
      if (d.selected.value !== id) return;
      sent.push(c);
      robotCommands.value = mergeCommands(robotCommands.value, [c]);
      robotRead.at = 0; // poll for its ack at once
    } catch (e) {
      error.value = `${kind === "goto_poi" ? "go to" : kind} refused: ${(e as Error).message}`;
    } finally {
      busy.value = false;
    }
  }

  return reactive({ marks, names, paused, recent, pois, error, busy, operator: computed(d.operator), tick, send });
}

export type CommandsState = ReturnType<typeof useCommands>;
