/**
 * The address bar holds what the page shows (the instant or live, speed and direction, the
 * map's view, the followed and selected robots, layers, panels, the change feed's filter,
 * the timeline's span, the plotted robots, the incidents panel's filters and pick, the heatmap), so a copied link opens the same page. Written
 * with replaceState (no history entry per frame), only when it changed.
 */
import type { Ref, ShallowRef } from "vue";
import type { ReplayEngine } from "../lib/engine";
import type { HeatmapState } from "../lib/heatmap";
import type { LayerToggles, MapView } from "../lib/mapview";
import { formatUrlState } from "../lib/urlstate";

export interface UrlSyncDeps {
  engine: ReplayEngine;
  view: ShallowRef<MapView | null>;
  toggles: LayerToggles;
  selected: Ref<string | null>;
  following: Ref<string | null>;
  panels: () => string[];
  area: () => [number, number, number, number] | null;
  changeRobot: Ref<string | null>;
  span: () => [number, number] | null;
  plotted: Ref<string[]>;
  /** The incidents panel's filters and pick. */
  incidents: () => { kinds: string[]; robot: string | null; picked: string | null };
  /** The heatmap shown (null: none). */
  heatmap: () => HeatmapState | null;
}

export function useUrlSync(d: UrlSyncDeps) {
  let lastUrl = "";

  function sync() {
    const c = d.engine.clock;
    const url = formatUrlState({
      live: c.live, t: d.engine.playhead, speed: c.speed, dir: c.direction, playing: c.playing,
      view: d.view.value ? d.view.value.view() : null, follow: d.following.value,
      layers: { ...d.toggles }, selected: d.selected.value,
      panels: d.panels(),
      area: d.area(),
      changeRobot: d.changeRobot.value,
      span: d.span(),
      plot: d.plotted.value,
      ...((i) => ({ incidentKinds: i.kinds, incidentRobot: i.robot, incident: i.picked }))(d.incidents()),
      heatmap: d.heatmap(),
    });
    if (url !== lastUrl) {
      lastUrl = url;
      history.replaceState(null, "", url);
    }
  }

  return { sync };
}
