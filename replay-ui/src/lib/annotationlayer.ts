/**
 * The annotations on the Leaflet map: zones (keep-out hatched red, speed limits tinted by
 * their value and labelled with it, notes outlined), points of interest (an icon by kind and
 * the name), the zone violations at the playhead, and the operator's tools: drawing a
 * polygon, placing a point, dragging the selected annotation. Geometry lives in
 * lib/annotations.ts; this module only draws and listens.
 */
import L from "leaflet";
import {
  centroid, hatchSegments, hatchSpacing, speedText, speedTint, type Annotation, type Point, type ZoneDoc, type ZoneViolation,
} from "./annotations";
import { latLngToPixel, metresToLatLng, pixelToMetres } from "./geo";
import type { MapMeta } from "./types";

const POI_GLYPH: Record<string, string> = { station: "S", charger: "⚡", door: "D", note: "i" };
const KEEP_OUT = "#d62728";
const SPEED = "#ff7f0e";
const NOTE = "#1f77b4";

function escapeHtml(s: string): string {
  return s.replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]!);
}

export interface AnnotationHandlers {
  select(id: string): void;
  /** The selected point dropped at (x, y), or the selected zone moved by (dx, dy), in metres. */
  movePoint(id: string, x: number, y: number): void;
  moveZone(id: string, dx: number, dy: number): void;
}

export class AnnotationLayer {
  readonly group = L.layerGroup();
  readonly violationGroup = L.layerGroup();
  /** What was drawn last, for the tests: ids of zones and points. */
  drawn: { zones: string[]; points: string[]; violations: string[] } = { zones: [], points: [], violations: [] };
  private preview = L.polyline([], { color: KEEP_OUT, weight: 2, dashArray: "4 4", interactive: false });
  private tool: { kind: "polygon"; vertices: Point[]; done: (v: Point[]) => void } | { kind: "point"; done: (x: number, y: number) => void } | null = null;

  /** What clicks and drops do (the page's annotations composable sets them). */
  on: AnnotationHandlers = { select: () => {}, movePoint: () => {}, moveZone: () => {} };

  constructor(private map: L.Map, private meta: () => MapMeta | null) {}

  private toLatLng(p: Point): L.LatLngExpression {
    return metresToLatLng(this.meta()!, p[0], p[1]);
  }

  private toMetres(ll: L.LatLng): Point {
    const m = pixelToMetres(this.meta()!, latLngToPixel(ll.lat, ll.lng));
    return [m.x, m.y];
  }

  /** Draws `list` (the annotations at the playhead); `editable`: the selected one can be dragged. */
  draw(list: Annotation[], selected: string | null, editable: boolean): void {
    this.group.clearLayers();
    this.drawn = { zones: [], points: [], violations: this.drawn.violations };
    if (!this.meta()) return;
    for (const a of list) {
      const doc = a.annotation;
      if (doc.shape === "zone") this.drawZone(a.id, doc, a.id === selected, editable);
      else {
        const on = a.id === selected;
        const icon = L.divIcon({
          className: "poi-icon",
          html: `<span class="poi poi-${escapeHtml(doc.kind)}${on ? " selected" : ""}" data-id="${escapeHtml(a.id)}">${POI_GLYPH[doc.kind] ?? "?"}</span>`
            + `<span class="poi-name">${escapeHtml(doc.name)}</span>`,
          iconSize: [20, 20], iconAnchor: [10, 10],
        });
        const m = L.marker(this.toLatLng([doc.x, doc.y]), { icon, draggable: on && editable, keyboard: false, title: `${doc.name} (${doc.kind})` });
        m.on("click", () => this.on.select(a.id));
        m.on("dragend", () => {
          const [x, y] = this.toMetres(m.getLatLng());
          this.on.movePoint(a.id, x, y);
        });
        m.addTo(this.group);
        this.drawn.points.push(a.id);
      }
    }
  }

  private drawZone(id: string, z: ZoneDoc, selected: boolean, editable: boolean): void {
    const colour = z.kind === "keep_out" ? KEEP_OUT : z.kind === "speed_limit" ? SPEED : NOTE;
    const rings = [z.polygon, ...(z.holes ?? [])].map((r) => r.map((p) => this.toLatLng(p)));
    const poly = L.polygon(rings as L.LatLngExpression[][], {
      color: colour, weight: selected ? 4 : 2,
      dashArray: z.kind === "note" ? "6 4" : undefined,
      fill: z.kind !== "note" || selected,
      fillColor: colour,
      fillOpacity: z.kind === "speed_limit" ? speedTint(z) : z.kind === "keep_out" ? 0.1 : 0.05,
    });
    poly.on("click", () => this.on.select(id));
    if (selected && editable) poly.on("mousedown", (e: L.LeafletMouseEvent) => this.dragZone(id, poly, e));
    poly.addTo(this.group);
    if (z.kind === "keep_out") {
      const hatch = hatchSegments(z, hatchSpacing(z.polygon)).map(([a, b]) => [this.toLatLng(a), this.toLatLng(b)]);
      L.polyline(hatch as L.LatLngExpression[][], { color: KEEP_OUT, weight: 1.5, opacity: 0.8, interactive: false }).addTo(this.group);
    }
    const label = z.kind === "speed_limit" ? `${z.name} · ≤ ${speedText(z)}` : z.name;
    L.marker(this.toLatLng(centroid(z.polygon)), {
      interactive: false, keyboard: false,
      icon: L.divIcon({ className: "zone-label", html: `<span class="zone-${z.kind}" data-id="${escapeHtml(id)}">${escapeHtml(label)}</span>`, iconSize: [0, 0] }),
    }).addTo(this.group);
    this.drawn.zones.push(id);
  }

  /** Drags the selected zone: the map stays put, the outline follows, the drop moves it. */
  private dragZone(id: string, poly: L.Polygon, e: L.LeafletMouseEvent): void {
    if (this.tool) return;
    L.DomEvent.stop(e.originalEvent);
    const start = e.latlng;
    const original = poly.getLatLngs() as L.LatLng[][];
    this.map.dragging.disable();
    const move = (m: L.LeafletMouseEvent) => {
      const dLat = m.latlng.lat - start.lat;
      const dLng = m.latlng.lng - start.lng;
      poly.setLatLngs(original.map((r) => r.map((p) => L.latLng(p.lat + dLat, p.lng + dLng))));
    };
    this.map.on("mousemove", move);
    this.map.once("mouseup", (u: L.LeafletMouseEvent) => {
      this.map.off("mousemove", move);
      this.map.dragging.enable();
      const [x0, y0] = this.toMetres(start);
      const [x1, y1] = this.toMetres(u.latlng);
      if (Math.hypot(x1 - x0, y1 - y0) > 1e-3) this.on.moveZone(id, x1 - x0, y1 - y0);
    });
  }

  /** Marks where robots stood inside keep-out zones (each one's latest at the playhead). */
  drawViolations(vs: ZoneViolation[]): void {
    this.violationGroup.clearLayers();
    this.drawn.violations = [];
    if (!this.meta()) return;
    for (const v of vs) {
      L.marker(this.toLatLng([v.x, v.y]), {
        keyboard: false,
        icon: L.divIcon({ className: "violation-icon", html: `<span class="violation" data-robot="${escapeHtml(v.robotId)}"></span>`, iconSize: [30, 30], iconAnchor: [15, 15] }),
      }).bindTooltip(`${v.robotId} inside keep-out zone ${v.zoneId} at ${new Date(v.ts_ms).toISOString()}`).addTo(this.violationGroup);
      this.drawn.violations.push(v.robotId);
    }
  }

  /** Clicks add vertices; finish() (double-click, Enter) hands them to `done`; cancel() (Esc) drops them. */
  startPolygon(done: (vertices: Point[]) => void): void {
    this.cancel();
    this.tool = { kind: "polygon", vertices: [], done };
    this.begin();
    this.map.doubleClickZoom.disable();
    this.preview.setLatLngs([]).addTo(this.map);
    this.map.on("dblclick", this.finish, this);
  }

  /** The next click on the map hands its point to `done`. */
  placePoint(done: (x: number, y: number) => void): void {
    this.cancel();
    this.tool = { kind: "point", done };
    this.begin();
  }

  get active(): "polygon" | "point" | null {
    return this.tool?.kind ?? null;
  }

  get vertices(): number {
    return this.tool?.kind === "polygon" ? this.tool.vertices.length : 0;
  }

  private begin(): void {
    this.map.getContainer().style.cursor = "crosshair";
    this.map.on("click", this.click, this);
    this.map.on("mousemove", this.hover, this);
  }

  private click(e: L.LeafletMouseEvent): void {
    const t = this.tool;
    if (!t) return;
    if (t.kind === "point") {
      this.end();
      const [x, y] = this.toMetres(e.latlng);
      t.done(x, y);
      return;
    }
    t.vertices.push(this.toMetres(e.latlng));
    this.preview.setLatLngs(t.vertices.map((p) => this.toLatLng(p)));
  }

  private hover(e: L.LeafletMouseEvent): void {
    const t = this.tool;
    if (t?.kind === "polygon" && t.vertices.length) {
      this.preview.setLatLngs([...t.vertices.map((p) => this.toLatLng(p)), e.latlng, this.toLatLng(t.vertices[0])]);
    }
  }

  finish(): void {
    const t = this.tool;
    if (t?.kind !== "polygon") return;
    this.end();
    t.done(t.vertices);
  }

  cancel(): void {
    this.end();
  }

  private end(): void {
    this.tool = null;
    this.map.off("click", this.click, this);
    this.map.off("mousemove", this.hover, this);
    this.map.off("dblclick", this.finish, this);
    this.map.doubleClickZoom.enable();
    this.map.getContainer().style.cursor = "";
    this.preview.remove();
  }

}
