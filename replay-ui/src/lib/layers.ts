/**
 * Leaflet layers for the chunk grid: the chunks themselves (canvas tiles), an overlay
 * colouring each chunk by age or writer, and the chunk borders.
 */
import L from "leaflet";
import { gridBounds } from "./geo";
import type { ChunkImages } from "./images";
import type { MapState } from "./mapstate";
import type { MapMeta } from "./types";

export const UNKNOWN_GREY = "rgb(205,205,205)";
/** Where the history holds no chunk at all: stripes, so it cannot be mistaken for a chunk
 * a robot painted grey ("unknown", 205) or one whose picture is still loading. */
export const NO_DATA_STRIPE = "rgb(236,236,236)";
export const NO_DATA_BACKGROUND = "rgb(250,250,250)";

export function fillNoData(ctx: CanvasRenderingContext2D, x0: number, y0: number, w: number, h: number): void {
  ctx.fillStyle = NO_DATA_BACKGROUND;
  ctx.fillRect(x0, y0, w, h);
  ctx.save();
  ctx.beginPath();
  ctx.rect(x0, y0, w, h);
  ctx.clip();
  ctx.strokeStyle = NO_DATA_STRIPE;
  ctx.lineWidth = 3;
  for (let d = -h; d < w; d += 10) {
    ctx.beginPath();
    ctx.moveTo(x0 + d, y0 + h);
    ctx.lineTo(x0 + d + h, y0);
    ctx.stroke();
  }
  ctx.restore();
}

/** The Leaflet internals the canvas overlay uses (private, so not in @types/leaflet). */
interface CanvasOverlayInternals {
  _image: HTMLCanvasElement | undefined;
  _zoomAnimated: boolean;
  options: L.ImageOverlayOptions & { pixelWidth: number; pixelHeight: number };
  _updateZIndex(): void;
}

/**
 * An ImageOverlay whose element is a canvas: Leaflet positions and zoom-animates it like
 * an image, and we draw into it.
 */
const CanvasOverlay = L.ImageOverlay.extend({
  _initImage(this: CanvasOverlayInternals) {
    const canvas: HTMLCanvasElement = (this._image = L.DomUtil.create("canvas", "leaflet-image-layer") as HTMLCanvasElement);
    if (this._zoomAnimated) L.DomUtil.addClass(canvas, "leaflet-zoom-animated");
    if (this.options.className) L.DomUtil.addClass(canvas, this.options.className);
    canvas.width = this.options.pixelWidth;
    canvas.height = this.options.pixelHeight;
    canvas.onselectstart = L.Util.falseFn;
    canvas.onmousemove = L.Util.falseFn;
    if (this.options.zIndex != null) this._updateZIndex();
  },
}) as unknown as new (
  url: string, bounds: L.LatLngBoundsExpression, options: CanvasOverlayInternals["options"],
) => L.ImageOverlay;

/** One canvas pixel per chunk, stretched over the grid (drawn pixelated). */
function makeCanvasOverlay(meta: MapMeta, className: string, opacity = 1): L.ImageOverlay {
  return new CanvasOverlay("", gridBounds(meta), {
    pixelWidth: meta.CHUNK_COLS, pixelHeight: meta.CHUNK_ROWS, className, opacity, interactive: false,
  });
}

/**
 * The chunks as Leaflet grid tiles: each 256 px screen tile is a canvas onto which the
 * chunk pictures it covers are drawn, scaled to the tile's zoom. Canvases are sized to
 * the screen, not to the map, so a chunk change re-uploads one or a few small tiles; a
 * change redraws just that chunk's rectangle in the tiles showing it.
 */
const TILE = 256;

/** A grid tile as Leaflet keeps it in its private `_tiles`. */
interface GridTile {
  el: HTMLCanvasElement;
  coords: L.Coords;
  current: boolean;
}

/** The chunk grid layer with the ChunkLayer that draws its tiles, and Leaflet's tiles. */
type ChunkGridInternals = L.GridLayer & { owner: ChunkLayer; _tiles?: Record<string, GridTile> };

const ChunkGridLayer = L.GridLayer.extend({
  createTile(this: ChunkGridInternals, coords: L.Coords) {
    const tile = L.DomUtil.create("canvas", "leaflet-tile chunk-tile") as HTMLCanvasElement;
    tile.width = TILE;
    tile.height = TILE;
    this.owner.drawTile(tile, coords);
    return tile;
  },
}) as unknown as new (options: L.GridLayerOptions) => L.GridLayer;

export class ChunkLayer {
  readonly overlay: L.GridLayer;
  /** Cells whose current hash is still downloading (or was never written: not here). */
  readonly waiting = new Map<number, string>();

  constructor(private meta: MapMeta, private state: MapState, private images: ChunkImages) {
    this.overlay = new ChunkGridLayer({
      tileSize: TILE, noWrap: true, updateWhenZooming: false, keepBuffer: 1, className: "chunk-tiles",
      bounds: L.latLngBounds(gridBounds(meta)), minZoom: -10, maxZoom: 10, minNativeZoom: -8, maxNativeZoom: 3,
    });
    (this.overlay as ChunkGridInternals).owner = this;
    images.onLoad = (hashes) => {
      const loaded = new Set(hashes);
      for (const [k, h] of this.waiting) if (loaded.has(h)) state.dirty.add(k);
    };
  }

  private tiles(): GridTile[] {
    return Object.values((this.overlay as ChunkGridInternals)._tiles ?? {});
  }

  /** Draws every chunk a new tile covers. */
  drawTile(tile: HTMLCanvasElement, coords: L.Coords): void {
    const ctx = tile.getContext("2d")!;
    ctx.imageSmoothingEnabled = false;
    const { CHUNK_WIDTH: cw, CHUNK_HEIGHT: ch } = this.meta;
    const s = Math.pow(2, coords.z);
    const col0 = (coords.x * TILE) / s;
    const row0 = (coords.y * TILE) / s;
    const span = TILE / s;
    const c0 = Math.max(0, Math.floor(col0 / cw));
    const c1 = Math.min(this.meta.CHUNK_COLS - 1, Math.floor((col0 + span - 1e-9) / cw));
    const r0 = Math.max(0, Math.floor(row0 / ch));
    const r1 = Math.min(this.meta.CHUNK_ROWS - 1, Math.floor((row0 + span - 1e-9) / ch));
    for (let r = r0; r <= r1; r++) for (let c = c0; c <= c1; c++) this.drawChunkIn(ctx, coords, r, c);
  }

  private drawChunkIn(ctx: CanvasRenderingContext2D, coords: L.Coords, row: number, col: number): void {
    const { CHUNK_WIDTH: cw, CHUNK_HEIGHT: ch } = this.meta;
    const s = Math.pow(2, coords.z);
    // Whole device pixels, so neighbouring chunks neither overlap nor leave seams.
    const x0 = Math.round(col * cw * s - coords.x * TILE);
    const y0 = Math.round(row * ch * s - coords.y * TILE);
    const x1 = Math.round((col + 1) * cw * s - coords.x * TILE);
    const y1 = Math.round((row + 1) * ch * s - coords.y * TILE);
    const k = row * 65536 + col;
    const cell = this.state.get(k);
    const img = cell ? this.images.get(cell.content_hash) : undefined;
    if (img) {
      ctx.drawImage(img, x0, y0, x1 - x0, y1 - y0);
      return;
    }
    if (!cell) {
      fillNoData(ctx, x0, y0, x1 - x0, y1 - y0);
      return;
    }
    ctx.fillStyle = UNKNOWN_GREY; // its picture is on the way
    ctx.fillRect(x0, y0, x1 - x0, y1 - y0);
    this.waiting.set(k, cell.content_hash);
    this.images.request(cell.content_hash, true);
  }

  /** Draws the cells changed since the last call; true when the picture is complete. */
  draw(): boolean {
    const dirty = this.state.dirty;
    if (dirty.size) {
      // One getContext per tile, not per chunk and tile: a seek can redraw a thousand chunks.
      const tiles = this.tiles().map((t) => ({ coords: t.coords, ctx: t.el.getContext("2d")! }));
      const { CHUNK_WIDTH: cw, CHUNK_HEIGHT: ch } = this.meta;
      for (const k of dirty) {
        const row = Math.floor(k / 65536);
        const col = k % 65536;
        this.waiting.delete(k);
        const cell = this.state.get(k);
        if (cell && !this.images.get(cell.content_hash)) {
          // Not drawn until its picture is here; the tile keeps the older picture meanwhile.
          this.waiting.set(k, cell.content_hash);
          this.images.request(cell.content_hash, true);
          continue;
        }
        for (const t of tiles) {
          const s = Math.pow(2, t.coords.z);
          const span = TILE / s;
          const col0 = (t.coords.x * TILE) / s;
          const row0 = (t.coords.y * TILE) / s;
          if ((col + 1) * cw <= col0 || col * cw >= col0 + span || (row + 1) * ch <= row0 || row * ch >= row0 + span) continue;
          this.drawChunkIn(t.ctx, t.coords, row, col);
        }
      }
      dirty.clear();
    }
    for (const [k, h] of this.waiting) {
      if (this.images.failed.has(h)) this.waiting.delete(k);
      else if (this.state.get(k)?.content_hash !== h) this.waiting.delete(k);
    }
    return this.waiting.size === 0 && this.tiles().length > 0;
  }

  clear(): void {
    this.waiting.clear();
    this.overlay.redraw();
  }

  /** The colour shown at a map pixel (read from the tile showing it at the current zoom). */
  pixel(row: number, col: number): [number, number, number, number] | null {
    for (const t of this.tiles()) {
      if (!t.current) continue;
      const s = Math.pow(2, t.coords.z);
      const x = Math.floor((col + 0.5) * s - t.coords.x * TILE);
      const y = Math.floor((row + 0.5) * s - t.coords.y * TILE);
      if (x < 0 || y < 0 || x >= TILE || y >= TILE) continue;
      const d = t.el.getContext("2d")!.getImageData(x, y, 1, 1).data;
      return [d[0], d[1], d[2], d[3]];
    }
    return null;
  }
}

export type InfoMode = "age" | "writer";

/** Colours each chunk by the age of its last write (green fresh, to blue old) or by writer. */
export class InfoLayer {
  readonly overlay: L.ImageOverlay;

  constructor(private meta: MapMeta) {
    this.overlay = makeCanvasOverlay(meta, "info-canvas", 0.45);
  }

  draw(state: MapState, t: number, mode: InfoMode): void {
    const canvas = (this.overlay as unknown as CanvasOverlayInternals)._image;
    const ctx = canvas?.getContext("2d");
    if (!ctx) return;
    ctx.clearRect(0, 0, ctx.canvas.width, ctx.canvas.height);
    for (const cell of state.cells.values()) {
      ctx.fillStyle = mode === "age" ? ageColour(t - cell.ts_ms) : writerColour(cell.robotId);
      ctx.fillRect(cell.column, cell.row, 1, 1);
    }
  }
}

/** The chunk-age legend: the ages at which `ageColour` is shown, and its colour there. */
export const AGE_LEGEND: [string, number][] = [
  ["1 min", 60_000], ["1 h", 3_600_000], ["1 day", 86_400_000], ["7 days", 7 * 86_400_000],
];

/** Fresh (seconds) -> hot red, an hour -> yellow, a day -> green, a week -> blue. */
export function ageColour(ageMs: number): string {
  const hours = Math.max(0, ageMs) / 3_600_000;
  const f = Math.min(1, Math.log10(1 + hours * 60) / Math.log10(1 + 168 * 60));
  return `hsl(${Math.round(f * 240)}, 90%, 50%)`;
}

export function writerColour(robotId: string): string {
  let h = 0;
  for (let i = 0; i < robotId.length; i++) h = (h * 31 + robotId.charCodeAt(i)) >>> 0;
  return `hsl(${h % 360}, 75%, 50%)`;
}

/** The chunk grid's borders as one polyline layer. */
export function gridLines(meta: MapMeta): L.Polyline {
  const lines: [number, number][][] = [];
  const w = meta.CHUNK_COLS * meta.CHUNK_WIDTH;
  const h = meta.CHUNK_ROWS * meta.CHUNK_HEIGHT;
  for (let r = 0; r <= meta.CHUNK_ROWS; r++) lines.push([[-r * meta.CHUNK_HEIGHT, 0], [-r * meta.CHUNK_HEIGHT, w]]);
  for (let c = 0; c <= meta.CHUNK_COLS; c++) lines.push([[0, c * meta.CHUNK_WIDTH], [-h, c * meta.CHUNK_WIDTH]]);
  return L.polyline(lines, { color: "#3388ff", weight: 1, opacity: 0.6, interactive: false });
}
