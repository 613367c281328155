/**
 * The replay page's VDA 5050 facts: the timeline span's error onsets (marks), the fleet's
 * facts of the hour before the playhead (each row's current errors; online/offline from
 * the exact connection states where one is in that hour, else the pose silence), and the
 * selected vehicle's facts with its factsheet (the fleet's until its own are read). The
 * marks are read as the page's other span lists are (lib/cadence.ts); the fleet's facts come
 * from the marks' read where it holds the hour before the playhead (live, a view of an hour
 * or more), else are read at most every 2 s of playhead, and no more than once a refresh
 * while the playhead stays within a read that reached ahead of now (live); the vehicle's
 * facts at most every 2 s of playhead.
 */
import { ref, shallowRef } from "vue";
import type { FleetRow } from "../lib/fleet";
import { mayGrow, readAheadTo, REFRESH_MS, stillAnswers, type SpanRead } from "../lib/cadence";
import { connectionAt, errorMarks, errorsAt, fleetFacts, isVehicleId, vehicleFacts, type ErrorMark, type VdaVehicle } from "../lib/vda";

const FLEET_WINDOW_MS = 3_600_000;
/** Marks only for spans up to this long: a longer one would read every vehicle state of
 * days (the clears) on each zoom; zoom in to see them. */
export const MARKS_MAX_SPAN_MS = 6 * 3_600_000;
const REREAD_MS = 2_000;

export function useVdaFacts(base: () => string) {
  const marks = shallowRef<ErrorMark[]>([]);
  const fleet = shallowRef(new Map<string, VdaVehicle>());
  const selected = ref<VdaVehicle | null>(null);
  /** The span the marks were read for, up to where (past a live span's end) and when. */
  let marksRead = { from: 0, to: 0, until: 0, at: 0 };
  /** The vehicles of the last marks' read, over [from, until). */
  let marksFacts: { from: number; until: number; vehicles: VdaVehicle[] } | null = null;
  /** Which read the fleet's facts come from (the marks' or its own). */
  let fleetFrom: object | null = null;
  /** The fleet's own read: for the instant `t`, up to `until`, made at `at`. */
  let fleetRead: SpanRead = { t: -Infinity, until: -Infinity, at: 0 };
  let fleetLoading = false;
  let selectedFor = { id: "", t: -Infinity };

  async function loadMarks(from: number | undefined, to: number | undefined) {
    if (from === undefined || to === undefined) return;
    const now = Date.now();
    // The view slides with live (or playback) every frame: read again only once it moved
    // by 2 % of its span or past what was read ahead, or at the refresh cadence while the
    // span reaches now (errors are stored as they happen).
    const slack = (to - from) / 50;
    const moved = Math.abs(from - marksRead.from) > slack || Math.abs(to - marksRead.to) > slack || to > marksRead.until;
    const stale = mayGrow(marksRead.until, marksRead.at) && now - marksRead.at > REFRESH_MS;
    if (!moved && !stale) return;
    const until = readAheadTo(to, now);
    marksRead = { from, to, until, at: now };
    if (to - from > MARKS_MAX_SPAN_MS) {
      marks.value = [];
      marksFacts = null;
      return;
    }
    try {
      const vehicles = await fleetFacts(base(), from, until);
      marksFacts = { from, until, vehicles };
      marks.value = errorMarks(vehicles);
    } catch {
      marks.value = [];
      marksFacts = null;
    }
  }

  async function loadFleet(t: number) {
    const m = marksFacts;
    if (m && m.from <= t - FLEET_WINDOW_MS && t < m.until) {
      // The marks' read holds the hour before the playhead: nothing to read for the fleet.
      if (fleetFrom !== m) fleet.value = new Map(m.vehicles.map((v) => [v.robotId, v]));
      fleetFrom = m;
      return;
    }
    const now = Date.now();
    if (fleetLoading || stillAnswers(fleetRead, t, now, REREAD_MS)) return;
    fleetLoading = true;
    const read = { t, until: readAheadTo(t + 1, now), at: now };
    fleetRead = read;
    try {
      fleet.value = new Map((await fleetFacts(base(), t - FLEET_WINDOW_MS, read.until)).map((v) => [v.robotId, v]));
      fleetFrom = read;
    } catch {
      fleet.value = new Map();
    } finally {
      fleetLoading = false;
    }
  }

  async function loadSelected(id: string | null, t: number) {
    if (!id || !isVehicleId(id)) {
      selected.value = null;
      selectedFor = { id: "", t: -Infinity };
      return;
    }
    if (id === selectedFor.id && Math.abs(t - selectedFor.t) <= REREAD_MS) return;
    selectedFor = { id, t };
    try {
      selected.value = await vehicleFacts(base(), id, t - FLEET_WINDOW_MS, t + 1);
    } catch {
      selected.value = null;
    }
  }

  /** The fleet rows with each vehicle's errors at `t` and its exact connection state. */
  function decorate(rows: FleetRow[], t: number): FleetRow[] {
    void loadFleet(t);
    for (const row of rows) {
      const v = fleet.value.get(row.robotId);
      row.errors = errorsAt(v, t);
      const c = connectionAt(v, t);
      if (c) {
        row.online = c.state === "ONLINE";
        row.connection = c.state;
      }
    }
    return rows;
  }

  /** What the details of `robotId` show: its own facts once read, until then the fleet's
   * (the same hour before the playhead), so that the details never say "online" from the
   * pose silence while its fleet row already shows the exact connection state. */
  function factsOf(robotId: string): VdaVehicle | null {
    const own = selected.value;
    return own && own.robotId === robotId ? own : (fleet.value.get(robotId) ?? null);
  }

  return { marks, selected, loadMarks, loadSelected, decorate, factsOf };
}
