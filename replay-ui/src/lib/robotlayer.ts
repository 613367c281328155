/**
 * Robots drawn on one canvas the size of the map's viewport, redrawn each frame: two
 * hundred robots cost one canvas, not two hundred moving DOM layers. Hit-testing for
 * clicks is done here too.
 */
import L from "leaflet";
import type { RobotView } from "./engine";
import { metresToLatLng } from "./geo";
import { placeLabels, robotColour } from "./fleet";
import { batteryColour, yawOfPose } from "./poses";
import { batteryScales } from "./battery";
import type { MapMeta } from "./types";

export interface RobotStyle {
  names: boolean;
  battery: boolean;
  paths: boolean;
  selected: string | null;
  /** The robots of the incident picked in the incidents panel: ringed in red. */
  highlighted: readonly string[];
}

export interface DrawnRobot {
  robotId: string;
  x: number; // container px
  y: number;
}

const RADIUS = 8;
const NEUTRAL = "#4a90d9";
export const HIGHLIGHT = "#d62728";

export class RobotLayer extends L.Layer {
  private canvas: HTMLCanvasElement | null = null;
  private robots: RobotView[] = [];
  /** Where each robot was drawn last (container coordinates), for clicks and tests. */
  drawn: DrawnRobot[] = [];
  /** Where each name label was drawn last (container px); robots whose label fits nowhere are absent. */
  labels: { robotId: string; x: number; y: number; w: number; h: number }[] = [];
  onClick: (id: string) => void = () => {};

  constructor(private meta: () => MapMeta | null, private style: () => RobotStyle) {
    super();
  }

  onAdd(map: L.Map): this {
    const canvas = (this.canvas = L.DomUtil.create("canvas", "robot-canvas leaflet-zoom-hide") as HTMLCanvasElement);
    map.getPanes().markerPane.appendChild(canvas);
    map.on("moveend zoomend resize viewreset", this.reset, this);
    map.on("move", this.redraw, this);
    map.on("click", this.click, this);
    map.on("mousemove", this.hover, this);
    this.reset();
    return this;
  }

  onRemove(map: L.Map): this {
    this.canvas?.remove();
    this.canvas = null;
    map.off("moveend zoomend resize viewreset", this.reset, this);
    map.off("move", this.redraw, this);
    map.off("click", this.click, this);
    map.off("mousemove", this.hover, this);
    return this;
  }

  private reset(): void {
    const map = this._map as L.Map | undefined;
    if (!map || !this.canvas) return;
    const size = map.getSize();
    const ratio = window.devicePixelRatio || 1;
    if (this.canvas.width !== size.x * ratio || this.canvas.height !== size.y * ratio) {
      this.canvas.width = size.x * ratio;
      this.canvas.height = size.y * ratio;
      this.canvas.style.width = `${size.x}px`;
      this.canvas.style.height = `${size.y}px`;
    }
    this.redraw();
  }

  update(robots: RobotView[]): void {
    this.robots = robots;
    this.redraw();
  }

  redraw(): void {
    const map = this._map as L.Map | undefined;
    const meta = this.meta();
    if (!map || !this.canvas || !meta) return;
    // The canvas stays over the viewport while the map pane is dragged.
    L.DomUtil.setPosition(this.canvas, map.containerPointToLayerPoint([0, 0]));
    const ctx = this.canvas.getContext("2d")!;
    const ratio = window.devicePixelRatio || 1;
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    const style = this.style();
    const size = map.getSize();
    const drawn: DrawnRobot[] = [];
    if (style.paths) {
      // Each robot's path in its own colour; the selected robot's last, solid and wide.
      const order = [...this.robots].sort((a, b) => Number(a.robotId === style.selected) - Number(b.robotId === style.selected));
      for (const r of order) {
        const path = r.pose.path;
        if (!path || !path.length) continue;
        const chosen = r.robotId === style.selected;
        ctx.strokeStyle = robotColour(r.robotId);
        ctx.lineWidth = chosen ? 5 : 2;
        ctx.globalAlpha = style.selected && !chosen ? 0.45 : 1;
        ctx.setLineDash(chosen ? [] : [4, 4]);
        ctx.beginPath();
        const start = map.latLngToContainerPoint(metresToLatLng(meta, r.x, r.y));
        ctx.moveTo(start.x, start.y);
        for (const [x, y] of path) {
          const p = map.latLngToContainerPoint(metresToLatLng(meta, x, y));
          ctx.lineTo(p.x, p.y);
        }
        ctx.stroke();
      }
      ctx.setLineDash([]);
      ctx.globalAlpha = 1;
    }
    ctx.font = "11px system-ui, sans-serif";
    for (const r of this.robots) {
      const p = map.latLngToContainerPoint(metresToLatLng(meta, r.x, r.y));
      drawn.push({ robotId: r.robotId, x: p.x, y: p.y });
      if (p.x < -50 || p.y < -50 || p.x > size.x + 200 || p.y > size.y + 50) continue;
      const yaw = r.yaw ?? yawOfPose(r.pose);
      ctx.save();
      ctx.globalAlpha = r.offline ? 0.4 : 1;
      ctx.translate(p.x, p.y);
      if (style.selected === r.robotId) {
        ctx.beginPath();
        ctx.arc(0, 0, RADIUS + 5, 0, 2 * Math.PI);
        ctx.strokeStyle = "#1f6feb";
        ctx.lineWidth = 3;
        ctx.stroke();
      }
      if (style.highlighted.includes(r.robotId)) {
        ctx.beginPath();
        ctx.arc(0, 0, RADIUS + 9, 0, 2 * Math.PI);
        ctx.strokeStyle = HIGHLIGHT;
        ctx.lineWidth = 3;
        ctx.setLineDash([5, 3]);
        ctx.stroke();
        ctx.setLineDash([]);
      }
      ctx.beginPath();
      ctx.arc(0, 0, RADIUS, 0, 2 * Math.PI);
      ctx.fillStyle = style.battery ? batteryColour(r.pose.battery_level, batteryScales.noted(r.robotId, r.pose.battery_level)) : NEUTRAL;
      ctx.fill();
      // The ring in the robot's own colour: the same as its path and its fleet-list swatch.
      ctx.lineWidth = 3;
      ctx.strokeStyle = robotColour(r.robotId);
      ctx.stroke();
      // Heading: counter-clockwise in the world is clockwise on a y-down screen.
      ctx.rotate(-yaw);
      ctx.beginPath();
      ctx.moveTo(RADIUS - 4, -5);
      ctx.lineTo(RADIUS + 5, 0);
      ctx.lineTo(RADIUS - 4, 5);
      ctx.closePath();
      ctx.fillStyle = "#222";
      ctx.fill();
      ctx.restore();
    }
    if (style.names) this.drawLabels(ctx, drawn, style.selected, size);
    this.drawn = drawn;
  }

  /** Names beside the markers, never overlapping (fleet.placeLabels); the selected robot's first. */
  private drawLabels(ctx: CanvasRenderingContext2D, drawn: DrawnRobot[], selected: string | null, size: L.Point): void {
    const visible = drawn.filter((d) => d.x > -50 && d.y > -50 && d.x < size.x + 200 && d.y < size.y + 50)
      .sort((a, b) => Number(b.robotId === selected) - Number(a.robotId === selected));
    const boxes = placeLabels(visible.map((d) => ({ x: d.x, y: d.y, w: ctx.measureText(d.robotId).width + 4, h: 14 })), RADIUS + 2);
    this.labels = [];
    visible.forEach((d, i) => {
      const b = boxes[i];
      if (!b) return;
      this.labels.push({ robotId: d.robotId, ...b });
      ctx.fillStyle = "rgba(255,255,255,0.85)";
      ctx.fillRect(b.x, b.y, b.w, b.h);
      ctx.fillStyle = "#222";
      ctx.fillText(d.robotId, b.x + 2, b.y + 11);
    });
  }

  /** The robot under a container point, if any (the topmost, i.e. drawn last). */
  hit(x: number, y: number): string | null {
    for (let i = this.drawn.length - 1; i >= 0; i--) {
      const d = this.drawn[i];
      if ((d.x - x) ** 2 + (d.y - y) ** 2 <= (RADIUS + 4) ** 2) return d.robotId;
    }
    return null;
  }

  private click(e: L.LeafletMouseEvent): void {
    const id = this.hit(e.containerPoint.x, e.containerPoint.y);
    if (id) this.onClick(id);
  }

  private hover(e: L.LeafletMouseEvent): void {
    const map = this._map;
    map.getContainer().style.cursor = this.hit(e.containerPoint.x, e.containerPoint.y) ? "pointer" : "";
  }
}
