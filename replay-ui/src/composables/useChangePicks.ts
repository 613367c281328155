/**
 * The change feed's filter (a robot, an area drawn on the map as a chunk box) and the
 * changes and conflicts picked from the feed and the conflict inspector: a pick pauses
 * just after it and outlines its chunk on the map.
 */
import { ref, type Ref, type ShallowRef } from "vue";
import { boxOfPixels, changeSearchRanges, fetchChanges, findNeighbourChange, seekTargetOf, type Change, type ChunkBox,
  type WriteDensity } from "../lib/changefeed";
import type { ReplayEngine } from "../lib/engine";
import { conflictKey, type ConflictEntry } from "../lib/inspect";
import type { MapView } from "../lib/mapview";
import type { UrlState } from "../lib/urlstate";

export interface ChangePickDeps {
  engine: ReplayEngine;
  view: ShallowRef<MapView | null>;
  initial: UrlState;
  /** The timeline's span and its chunk writes per bucket (null: not read yet). */
  span: () => [number, number];
  density: () => WriteDensity | null;
  /** The change feed is open: Shift+←/→ step through what it lists (its robot and area). */
  feedOpen: () => boolean;
  /** Leaves live mode, pauses and seeks to an instant. */
  pauseAt: (t: number) => void;
  notice: Ref<string | null>;
}

export function useChangePicks(d: ChangePickDeps) {
  const { engine, view, initial } = d;
  const changeRobot = ref<string | null>(initial.changeRobot);
  const changeBox = ref<ChunkBox | null>(initial.area ? { rowMin: initial.area[0], rowMax: initial.area[1], colMin: initial.area[2], colMax: initial.area[3] } : null);
  const drawing = ref(false);
  /** The key of the change or conflict picked last (its list highlights it). */
  const activeChange = ref<string | null>(null);

  /** Seeks just after a change of the feed and outlines its chunk. */
  function pickChange(c: Change) {
    activeChange.value = `${c.ts_ms}:${c.row}:${c.column}:${c.robot_id}`;
    view.value?.outlineChunk(c.kind === "change" ? { row: c.row, column: c.column } : null);
    d.pauseAt(seekTargetOf(c));
  }

  /** Seeks just after a conflict's later write (the map shows it and its box) and outlines its chunk. */
  function pickConflict(c: ConflictEntry) {
    activeChange.value = conflictKey(c);
    view.value?.outlineChunk(c);
    d.pauseAt(c.seek_ms);
  }

  /**
   * Shift+←/→: to the previous/next change from the playhead, whatever panel is open: the
   * timeline's counts say where changes can be, the change feed reads them there (with the
   * feed's robot and area while it is open). Presses while one is being looked for are dropped.
   */
  let stepping = false;
  function stepChange(dir: 1 | -1): void {
    void findAndPick(dir);
  }
  async function findAndPick(dir: 1 | -1) {
    if (stepping) return;
    stepping = true;
    const filtered = d.feedOpen() && (changeRobot.value !== null || changeBox.value !== null);
    const filter = filtered ? { robot: changeRobot.value, box: changeBox.value } : { robot: null, box: null };
    const from = engine.playhead;
    try {
      const ranges = changeSearchRanges(d.density(), d.span(), from, dir);
      const c = await findNeighbourChange((a, b, before) => fetchChanges(engine.api.base, a, b, filter, dir > 0 ? 1000 : 20, before), ranges, from, dir);
      if (c) pickChange(c);
      else {
        d.notice.value = `no ${dir > 0 ? "later" : "earlier"} change in the timeline's span${filtered ? " with the change feed's robot and area" : ""}: zoom out to look further`;
      }
    } catch (e) {
      d.notice.value = `the ${dir > 0 ? "next" : "previous"} change could not be read: ${(e as Error).message}`;
    } finally {
      stepping = false;
    }
  }

  function drawArea() {
    if (!view.value) return;
    drawing.value = true;
    view.value.drawArea((a, b) => {
      drawing.value = false;
      const box = engine.meta ? boxOfPixels(engine.meta, a, b) : null;
      changeBox.value = box;
      view.value?.showArea(box);
    });
  }

  function clearArea() {
    changeBox.value = null;
    view.value?.showArea(null);
  }

  /** The area as the address keeps it: [rowMin, rowMax, colMin, colMax]. */
  function area(): [number, number, number, number] | null {
    const b = changeBox.value;
    return b ? [b.rowMin, b.rowMax, b.colMin, b.colMax] : null;
  }

  /** Once the map is there: the area the address named. */
  function attach(v: MapView) {
    if (changeBox.value) v.showArea(changeBox.value);
  }

  return { changeRobot, changeBox, drawing, activeChange, pickChange, pickConflict, stepChange, drawArea, clearArea, area, attach };
}
