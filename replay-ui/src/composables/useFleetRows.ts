/**
 * The robots the panels list: the fleet panel's rows (with their speeds, from the fleet's
 * last seconds of poses before the playhead: read from the API when replaying, the live
 * stream's when live; and their VDA 5050 facts), and the robot ids
 * the change feed and the plots offer.
 */
import { ref } from "vue";
import type { ReplayEngine } from "../lib/engine";
import { fleetRows, recentTracks, type FleetRow } from "../lib/fleet";
import type { Pose } from "../lib/types";

/** The speeds' poses are read again once the playhead moved this far (one request at a time). */
const SPEEDS_REREAD_MS = 2000;

export function useFleetRows(engine: ReplayEngine, decorate: (rows: FleetRow[], t: number) => FleetRow[]) {
  const fleet = ref<FleetRow[]>([]);
  const fleetSearch = ref("");
  const robotIds = ref<string[]>([]);
  let speedTracks = new Map<string, Pose[]>();
  let speedFor = -Infinity;
  let speedLoading = false;

  async function loadSpeeds() {
    speedLoading = true;
    speedFor = engine.playhead;
    try {
      speedTracks = await recentTracks(engine.api.base, speedFor);
    } catch {
      speedTracks = new Map();
    } finally {
      speedLoading = false;
    }
  }

  /** The fleet panel's rows at the playhead; returns how many robots there are. Live, the
   * speeds come from the stream's poses (engine.liveTracks): nothing is read for them. */
  function refreshRows(): number {
    const robots = engine.robots();
    const live = engine.clock.live;
    const tracks = live ? engine.liveTracks : speedTracks;
    fleet.value = decorate(fleetRows(robots, tracks, engine.playhead, fleetSearch.value), engine.playhead);
    if (!live && !speedLoading && Math.abs(engine.playhead - speedFor) > SPEEDS_REREAD_MS) void loadSpeeds();
    return robots.length;
  }

  /** The robot ids at the playhead, sorted (a new list only when they changed). */
  function refreshIds() {
    const ids = engine.robots().map((r) => r.robotId).sort();
    if (ids.join() !== robotIds.value.join()) robotIds.value = ids;
  }

  return { fleet, fleetSearch, robotIds, refreshRows, refreshIds };
}
