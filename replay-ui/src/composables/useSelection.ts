/**
 * The selected robot and the one the map follows: the details shown for the selected one
 * (refreshed with the playhead) and its trail, the last ten minutes before the playhead.
 */
import { ref, watch, type ShallowRef } from "vue";
import type { ReplayEngine, RobotView } from "../lib/engine";
import { robotColour } from "../lib/fleet";
import type { MapView } from "../lib/mapview";
import { robotStatus, type RobotStatus } from "../lib/poses";
import { trailRuns, trailShown } from "../lib/trail";

/** The trail's length before the playhead; a point every TRAIL_STEP_MS. */
const TRAIL_MS = 600_000;
const TRAIL_STEP_MS = 5000;

export interface SelectionDeps {
  engine: ReplayEngine;
  view: ShallowRef<MapView | null>;
  /** From the address: the selected robot and the followed one. */
  selected: string | null;
  follow: string | null;
  /** The oldest instant the history keeps (the trail starts no earlier). */
  oldestMs: () => number;
}

export function useSelection(d: SelectionDeps) {
  const { engine, view } = d;
  const selected = ref<string | null>(d.selected);
  const following = ref<string | null>(d.follow);
  const selectedInfo = ref<{ view: RobotView; status: RobotStatus } | null>(null);
  let trailFor = { id: "", at: 0 };

  let shownInfo = "null";
  function refreshSelected() {
    const r = selected.value ? engine.robots().find((x) => x.robotId === selected.value) : undefined;
    // Online as the robot is drawn: exact at a resting playhead, allowing for the sampling step while playing fast.
    const info = r ? { view: r, status: { ...robotStatus(r.pose, engine.robotInfo.get(r.robotId), engine.playhead), online: !r.offline } } : null;
    // Written only when it reads otherwise: the details do not re-render with every summary of a resting page.
    const text = JSON.stringify(info);
    if (text === shownInfo) return;
    shownInfo = text;
    selectedInfo.value = info;
  }

  /** Drawn while playing no faster than 60x (lib/trail.ts): at 3600x it lags far behind the robot. */
  const shown = () => trailShown(engine.clock.playing, engine.clock.live, engine.clock.speed);

  async function loadTrail() {
    const id = selected.value;
    const t = engine.playhead;
    trailFor = { id: id ?? "", at: t };
    if (!id || !shown()) {
      view.value?.showTrail([]);
      return;
    }
    try {
      const points = await engine.api.track(id, Math.max(d.oldestMs(), t - TRAIL_MS), t + 1, TRAIL_STEP_MS);
      const runs = trailRuns(points.map((p) => ({ ts_ms: p.ts_ms, x: p.position[0], y: p.position[1] })));
      if (trailFor.id === id) view.value?.showTrail(runs, robotColour(id));
    } catch {
      view.value?.showTrail([]);
    }
  }

  watch(selected, () => {
    refreshSelected();
    void loadTrail();
  });

  function follow(id: string | null) {
    following.value = id;
    if (view.value) view.value.follow = id;
  }

  function selectAndFollow(id: string) {
    selected.value = id;
    follow(id);
  }

  function unselect() {
    selected.value = null;
    follow(null);
  }

  /** A click on a robot selects it; dragging the map stops following. */
  function attach(v: MapView) {
    v.onRobotClick = (id) => (selected.value = id);
    v.follow = following.value;
    v.map.on("dragstart", () => follow(null));
  }

  /** With the summary: the details at the playhead, the trail again once the playhead moved on
   * (by 30 s of data, more at high speeds). */
  function tick() {
    if (!selected.value) return;
    refreshSelected();
    if (!shown()) {
      if (trailFor.at !== -1) view.value?.showTrail([]);
      trailFor = { id: selected.value, at: -1 };
      return;
    }
    if (Math.abs(engine.playhead - trailFor.at) > 30_000 * Math.max(1, engine.clock.speed / 60)) void loadTrail();
  }

  return { selected, following, selectedInfo, follow, selectAndFollow, unselect, attach, tick };
}
