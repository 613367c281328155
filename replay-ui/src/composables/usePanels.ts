/**
 * What the page shows besides the map's floor, as the address keeps it: the map's layers,
 * the open side panels, and the robots pinned to the plots.
 */
import { computed, reactive, ref, type Ref } from "vue";
import type { LayerToggles } from "../lib/mapview";
import { PANELS, type UrlState } from "../lib/urlstate";

export type Panel = (typeof PANELS)[number];

const DEFAULT_LAYERS: LayerToggles = {
  names: true, battery: true, paths: true, borders: false, info: false, infoMode: "age", conflicts: true, annotations: true,
};

export function usePanels(initial: UrlState, selected: Ref<string | null>) {
  const toggles = reactive<LayerToggles>(initial.layers ?? { ...DEFAULT_LAYERS });
  /** The side panels that are open. */
  const panels = reactive(Object.fromEntries(PANELS.map((p) => [p, initial.panels.includes(p)])) as Record<Panel, boolean>);
  /** The robots on the plots besides the selected one, which is always plotted. */
  const plotPinned = ref<string[]>(initial.plot);
  /** Plotted: the selected robot, then the ones pinned to the plots. */
  const plotRobots = computed(() => [...new Set([...(selected.value ? [selected.value] : []), ...plotPinned.value])]);

  /** The plots' robot picker: the selected robot taken off the plots is unselected. */
  function setPlotRobots(ids: string[]) {
    if (selected.value && !ids.includes(selected.value)) selected.value = null;
    plotPinned.value = ids.filter((id) => id !== selected.value);
  }

  /** The robot details' "plot": pins the selected robot and opens the plots. */
  function plotSelected() {
    const id = selected.value;
    if (id && !plotPinned.value.includes(id)) plotPinned.value = [...plotPinned.value, id];
    panels.plots = true;
  }

  const openPanels = () => PANELS.filter((p) => panels[p]);

  return { toggles, panels, plotPinned, plotRobots, setPlotRobots, plotSelected, openPanels };
}
