/**
 * The Leaflet side: a non-geographic map (L.CRS.Simple, one unit per map pixel) with the
 * chunk tiles, info overlay, grid, conflicts, and the robots' canvas.
 */
import L from "leaflet";
import { AnnotationLayer } from "./annotationlayer";
import type { RobotView } from "./engine";
import { chunkBounds, gridBounds, latLngToPixel, metresToLatLng, metresToPixel, pixelToLatLng, resolutionOf, type Pixel } from "./geo";
import type { ChunkImages } from "./images";
import { ChunkLayer, gridLines, InfoLayer, type InfoMode } from "./layers";
import type { MapState } from "./mapstate";
import { RobotLayer } from "./robotlayer";
import { robotColour } from "./fleet";
import type { Conflict, MapMeta } from "./types";

export interface LayerToggles {
  names: boolean;
  battery: boolean;
  paths: boolean;
  borders: boolean;
  info: boolean;
  infoMode: InfoMode;
  conflicts: boolean;
  annotations: boolean;
}

/** The pane of the picked chunk's outline. */
const PICKED_PANE = "picked";
/** The heatmap's pane: over the floor's chunks, under the picked outline and the robots. */
const HEATMAP_PANE = "heatmap";

export class MapView {
  readonly map: L.Map;
  chunks: ChunkLayer | null = null;
  info: InfoLayer | null = null;
  grid: L.Polyline | null = null;
  conflictLayer = L.layerGroup();
  /** The selected robot's recent track (from /api/v1/robots/{id}/track). */
  trail = L.polyline([], { color: "#1f6feb", weight: 2, opacity: 0.7, interactive: false });
  robots: RobotLayer;
  /** Points of interest, zones and zone violations at the playhead, and the editing tools. */
  annotations: AnnotationLayer;
  toggles: LayerToggles | null = null;
  selected: string | null = null;
  /** The robots of the picked incident (ringed), its place and its robots' trails. */
  highlighted: string[] = [];
  incidentLayer = L.layerGroup();
  /** The heatmap's picture over the floor (lib/heatmap.ts), or none. */
  heatmap: L.ImageOverlay | null = null;
  meta: MapMeta | null = null;
  follow: string | null = null;
  onRobotClick: (id: string) => void = () => {};
  /** The change the feed's panel points at (drawn above the conflict boxes, in a pane of its
   * own: a box redrawn at every seek would else cover it), and the area the feed is filtered by. */
  changeOutline = L.rectangle([[0, 0], [0, 0]], { color: "#ff8c00", weight: 4, fill: false, interactive: false, pane: PICKED_PANE });
  areaRect = L.rectangle([[0, 0], [0, 0]], { color: "#6f42c1", weight: 2, dashArray: "6 4", fillOpacity: 0.06, interactive: false });
  private fitted = false;
  /** The conflicts the boxes show (redrawn only when they change: the loop asks twice a second). */
  private conflictsShown = "";
  private drawing: { done: (a: Pixel, b: Pixel) => void; start: L.LatLng | null } | null = null;

  constructor(el: HTMLElement, private state: MapState, private images: ChunkImages) {
    this.map = L.map(el, { crs: L.CRS.Simple, minZoom: -6, maxZoom: 5, zoomSnap: 0.25, attributionControl: false, preferCanvas: true,
      // Tiles appear at once: a seek shows the map at T, not a cross-fade from the old one.
      fadeAnimation: false,
      // The arrow keys step through time (the page's shortcuts), not pan the map.
      keyboard: false });
    this.map.setView([0, 0], 0);
    // Above the overlay pane (400: chunks, conflict boxes, trail), below the markers (600).
    this.map.createPane(PICKED_PANE).style.zIndex = "450";
    this.map.createPane(HEATMAP_PANE).style.zIndex = "420";
    this.robots = new RobotLayer(() => this.meta, () => ({
      names: this.toggles?.names ?? true, battery: this.toggles?.battery ?? true,
      paths: this.toggles?.paths ?? true, selected: this.selected, highlighted: this.highlighted,
    }));
    this.robots.onClick = (id) => this.onRobotClick(id);
    this.robots.addTo(this.map);
    this.trail.addTo(this.map);
    this.incidentLayer.addTo(this.map);
    this.annotations = new AnnotationLayer(this.map, () => this.meta);
  }

  /** (Re)builds the map layers for a meta; keeps the view unless it is the first one. */
  setMeta(meta: MapMeta, toggles: LayerToggles, view?: { lat: number; lng: number; zoom: number } | null): void {
    const same = this.meta && JSON.stringify(this.meta) === JSON.stringify(meta);
    if (same) {
      // Each seek parses a new but equal meta: adopt it, so the next frame skips this check.
      this.meta = meta;
      return;
    }
    this.meta = meta;
    this.conflictsShown = "";
    this.chunks?.overlay.remove();
    this.info?.overlay.remove();
    this.grid?.remove();
    this.chunks = new ChunkLayer(meta, this.state, this.images);
    this.chunks.overlay.addTo(this.map);
    this.chunks.clear();
    for (const k of this.state.cells.keys()) this.state.dirty.add(k);
    this.info = new InfoLayer(meta);
    this.grid = gridLines(meta);
    this.applyToggles(toggles);
    if (view) this.map.setView([view.lat, view.lng], view.zoom, { animate: false });
    else if (!this.fitted) this.map.fitBounds(gridBounds(meta), { animate: false });
    this.fitted = true;
  }

  applyToggles(t: LayerToggles): void {
    if (!this.meta) return;
    this.toggles = t;
    this.robots.redraw();
    if (this.grid) this.toggle(this.grid, t.borders);
    if (this.info) this.toggle(this.info.overlay, t.info);
    this.toggle(this.conflictLayer, t.conflicts);
    this.toggle(this.annotations.group, t.annotations);
    this.toggle(this.annotations.violationGroup, t.annotations);
  }

  private toggle(layer: L.Layer, on: boolean): void {
    if (on && !this.map.hasLayer(layer)) layer.addTo(this.map);
    if (!on && this.map.hasLayer(layer)) layer.remove();
  }

  /** Draws the changed chunks; true when every chunk shown has its picture. */
  drawChunks(): boolean {
    return this.chunks ? this.chunks.draw() : false;
  }

  drawInfo(t: number, mode: InfoMode): void {
    if (this.info && this.map.hasLayer(this.info.overlay)) this.info.draw(this.state, t, mode);
  }

  updateRobots(robots: RobotView[]): void {
    if (!this.meta) return;
    if (this.follow) {
      const r = robots.find((x) => x.robotId === this.follow);
      if (r) this.map.panTo(metresToLatLng(this.meta, r.x, r.y), { animate: false });
    }
    this.robots.update(robots);
  }

  /** The selected robot's recent track (its runs, lib/trail.ts), wide and in the robot's own colour (its marker ring and path's). */
  showTrail(runs: { x: number; y: number }[][], colour = "#1f6feb"): void {
    const meta = this.meta;
    this.trail.setStyle({ color: colour, weight: 4, opacity: 0.85 });
    this.trail.setLatLngs(meta ? runs.map((run) => run.map((p) => metresToLatLng(meta, p.x, p.y))) : []);
  }

  /**
   * The picked incident (null: none): its robots ringed, its place marked in its kind's
   * colour, and each robot's trail around it (its runs, lib/trail.ts) in the robot's colour.
   */
  showIncident(incident: { robots: string[]; x: number; y: number; colour: string; title: string } | null,
    trails: Map<string, { x: number; y: number }[][]> = new Map()): void {
    this.incidentLayer.clearLayers();
    this.highlighted = incident ? incident.robots : [];
    this.robots.redraw();
    const meta = this.meta;
    if (!incident || !meta) return;
    for (const [id, runs] of trails) {
      L.polyline(runs.map((run) => run.map((p) => metresToLatLng(meta, p.x, p.y))),
        { color: robotColour(id), weight: 3, opacity: 0.9, interactive: false }).addTo(this.incidentLayer);
    }
    L.circleMarker(metresToLatLng(meta, incident.x, incident.y),
      { radius: 14, color: incident.colour, weight: 3, fillOpacity: 0.15, interactive: true })
      .bindTooltip(incident.title).addTo(this.incidentLayer);
  }

  /** The heatmap's picture (`url`: its cells' box, north up) over the box's corners in
   * metres (lowest x and y, highest x and y); null: none. True when it is drawn. */
  showHeatmap(url: string | null, box: { x0: number; y0: number; x1: number; y1: number } | null): boolean {
    this.heatmap?.remove();
    this.heatmap = null;
    const meta = this.meta;
    if (!url || !box || !meta) return !url;
    const bounds = L.latLngBounds(metresToLatLng(meta, box.x0, box.y0), metresToLatLng(meta, box.x1, box.y1));
    this.heatmap = L.imageOverlay(url, bounds, { pane: HEATMAP_PANE, className: "heatmap", interactive: false }).addTo(this.map);
    return true;
  }

  /** Metres one screen pixel spans at the view's zoom (0 before a map is known). */
  metresPerScreenPixel(): number {
    return this.meta ? resolutionOf(this.meta) / 2 ** this.map.getZoom() : 0;
  }

  showConflicts(conflicts: Conflict[], t: number, windowMs: number): void {
    const meta = this.meta;
    const shown = meta ? conflicts.filter((c) => c.ts_ms <= t && c.ts_ms >= t - windowMs) : [];
    const key = shown.map((c) => `${c.ts_ms}:${c.row}:${c.column}:${c.robot_a}:${c.robot_b}`).join();
    if (key === this.conflictsShown) return;
    this.conflictsShown = key;
    this.conflictLayer.clearLayers();
    if (!meta) return;
    for (const c of shown) {
      L.rectangle(chunkBounds(meta, c.row, c.column), { color: "#e00", weight: 3, fill: false, interactive: true })
        .bindTooltip(`conflict ${c.robot_a} / ${c.robot_b} at ${new Date(c.ts_ms).toISOString()}`)
        .addTo(this.conflictLayer);
    }
  }

  /** Outlines a chunk (null: none). */
  outlineChunk(chunk: { row: number; column: number } | null): void {
    if (!chunk || !this.meta) {
      this.changeOutline.remove();
      return;
    }
    this.changeOutline.setBounds(L.latLngBounds(chunkBounds(this.meta, chunk.row, chunk.column)));
    if (!this.map.hasLayer(this.changeOutline)) this.changeOutline.addTo(this.map);
  }

  /** Shows the area (a chunk box) the change feed is filtered by (null: none). */
  showArea(box: { rowMin: number; rowMax: number; colMin: number; colMax: number } | null): void {
    if (!box || !this.meta) {
      this.areaRect.remove();
      return;
    }
    const a = chunkBounds(this.meta, box.rowMin, box.colMin)[0];
    const b = chunkBounds(this.meta, box.rowMax, box.colMax)[1];
    this.areaRect.setBounds(L.latLngBounds([a, b]));
    if (!this.map.hasLayer(this.areaRect)) this.areaRect.addTo(this.map);
  }

  /** The next drag on the map draws a rectangle instead of panning; `done` gets its corners (map pixels). */
  drawArea(done: (a: Pixel, b: Pixel) => void): void {
    this.drawing = { done, start: null };
    this.map.dragging.disable();
    this.map.getContainer().style.cursor = "crosshair";
    this.map.once("mousedown", (e: L.LeafletMouseEvent) => {
      if (!this.drawing) return;
      this.drawing.start = e.latlng;
      this.areaRect.setBounds(L.latLngBounds(e.latlng, e.latlng));
      if (!this.map.hasLayer(this.areaRect)) this.areaRect.addTo(this.map);
      this.map.on("mousemove", this.drawMove, this);
      this.map.once("mouseup", (u: L.LeafletMouseEvent) => {
        const d = this.drawing;
        this.map.off("mousemove", this.drawMove, this);
        this.map.dragging.enable();
        this.map.getContainer().style.cursor = "";
        this.drawing = null;
        if (d?.start) d.done(latLngToPixel(d.start.lat, d.start.lng), latLngToPixel(u.latlng.lat, u.latlng.lng));
      });
    });
  }

  private drawMove(e: L.LeafletMouseEvent): void {
    if (this.drawing?.start) this.areaRect.setBounds(L.latLngBounds(this.drawing.start, e.latlng));
  }

  fitGrid(): void {
    if (this.meta) this.map.fitBounds(gridBounds(this.meta), { animate: false });
  }

  /**
   * A "whole floor" button under the zoom buttons: the floor fitted in view. `first` runs
   * before (the page stops following a robot there, which would pan the floor away again).
   */
  addWholeFloorButton(first: () => void): void {
    const fit = () => {
      first();
      this.fitGrid();
    };
    const WholeFloor = L.Control.extend({
      onAdd: () => {
        const bar = L.DomUtil.create("div", "leaflet-bar");
        const a = L.DomUtil.create("a", "whole-floor", bar);
        a.href = "#";
        a.textContent = "whole floor";
        a.title = "Show the whole floor (stops following a robot)";
        a.setAttribute("role", "button");
        a.dataset.testid = "whole-floor";
        L.DomEvent.disableClickPropagation(bar);
        L.DomEvent.on(a, "click", (e) => {
          L.DomEvent.preventDefault(e);
          fit();
        });
        return bar;
      },
    });
    new WholeFloor({ position: "topleft" }).addTo(this.map);
  }

  /** Where the robots were drawn, in page coordinates. */
  drawnRobots(): { robotId: string; x: number; y: number }[] {
    const r = this.map.getContainer().getBoundingClientRect();
    return this.robots.drawn.map((d) => ({ robotId: d.robotId, x: r.left + d.x, y: r.top + d.y }));
  }

  /** The page point (CSS px, relative to the viewport) of a map pixel. */
  screenPointOfPixel(row: number, col: number): { x: number; y: number } {
    const p = this.map.latLngToContainerPoint(pixelToLatLng({ row, col }));
    const r = this.map.getContainer().getBoundingClientRect();
    return { x: r.left + p.x, y: r.top + p.y };
  }

  screenPointOfMetres(x: number, y: number): { x: number; y: number } {
    const p = metresToPixel(this.meta!, x, y);
    return this.screenPointOfPixel(p.row, p.col);
  }

  view(): { lat: number; lng: number; zoom: number } {
    const c = this.map.getCenter();
    return { lat: Math.round(c.lat * 10) / 10, lng: Math.round(c.lng * 10) / 10, zoom: this.map.getZoom() };
  }
}
