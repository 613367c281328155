/**
 * Chunk pictures by content hash: each distinct hash is fetched once, decoded once, and
 * kept in a bounded LRU of decoded bitmaps.
 *
 * Hashes asked for in the same task (a seek asks for every chunk of the map at once) are
 * fetched together through the batch endpoint, in a few slices a few at a time, and
 * inflated here: a seek costs a few requests and one database read per slice instead of
 * one request and one read per picture.
 */
import { greyToRgba, inflate, slicesFor, type ChunkBatch, type ChunkContent } from "./chunkdecode";
import { ApiError, BUSY } from "./request";

export type ChunkImage = ImageBitmap | HTMLImageElement | HTMLCanvasElement | OffscreenCanvas;

export interface ChunkSource {
  chunkBatch(hashes: string[]): Promise<ChunkBatch>;
}

export interface ChunkImagesOptions {
  /** Batch requests in flight at once. */
  parallel?: number;
  capacity?: number;
  decode?: (c: ChunkContent) => ChunkImage;
}

export class ChunkImages {
  private ready = new Map<string, ChunkImage>();
  private requested = new Set<string>();
  private queue: string[] = [];
  private active = 0;
  private scheduled = false;
  /** Pictures downloaded (each distinct hash once). */
  fetched = 0;
  /** HTTP requests made for pictures (batches). */
  requests = 0;
  failed = new Set<string>();
  /** Hashes that just became available (one call per batch). */
  onLoad: (hashes: string[]) => void = () => {};
  /** After each batch answered or given up on (the page's frame loop wakes to draw, or to stop waiting). */
  afterBatch: () => void = () => {};
  readonly parallel: number;
  readonly capacity: number;
  private decode: (c: ChunkContent) => ChunkImage;

  constructor(private source: ChunkSource, opts: ChunkImagesOptions = {}) {
    this.parallel = opts.parallel ?? 4;
    this.capacity = opts.capacity ?? 6000;
    this.decode = opts.decode ?? decodeContent;
  }

  get(hash: string): ChunkImage | undefined {
    const img = this.ready.get(hash);
    if (img) {
      this.ready.delete(hash); // refresh its place in the LRU
      this.ready.set(hash, img);
    }
    return img;
  }

  has(hash: string): boolean {
    return this.ready.has(hash);
  }

  /** Asks for a hash (no-op if loaded or asked); `urgent` jumps the prefetch queue. */
  request(hash: string, urgent = false): void {
    if (!hash || this.ready.has(hash) || this.failed.has(hash)) return;
    if (this.requested.has(hash)) {
      if (urgent) {
        const i = this.queue.indexOf(hash);
        if (i > 0) this.queue.unshift(...this.queue.splice(i, 1));
      }
      return;
    }
    this.requested.add(hash);
    if (urgent) this.queue.unshift(hash);
    else this.queue.push(hash);
    this.schedule();
  }

  /** Asks for many hashes, in this order: ahead of anything queued before, or after it. */
  requestMany(hashes: Iterable<string>, front = true): void {
    const fresh: string[] = [];
    const again = new Set<string>();
    for (const h of hashes) {
      if (!h || this.ready.has(h) || this.failed.has(h)) continue;
      if (this.requested.has(h)) again.add(h);
      else {
        this.requested.add(h);
        fresh.push(h);
      }
    }
    if (!front) this.queue.push(...fresh);
    else {
      const rest = again.size ? this.queue.filter((h) => !again.has(h)) : this.queue;
      this.queue = [...fresh, ...this.queue.filter((h) => again.has(h)), ...rest];
    }
    if (this.queue.length) this.schedule();
  }

  get queued(): number {
    return this.queue.length + this.active;
  }

  /** Pumps once the current task has asked for everything it needs (one batch, not N). */
  private schedule(): void {
    if (this.scheduled) return;
    this.scheduled = true;
    queueMicrotask(() => {
      this.scheduled = false;
      this.pump();
    });
  }

  private pump(): void {
    while (this.active < this.parallel && this.queue.length) {
      const [slice] = slicesFor(this.queue, this.parallel - this.active);
      this.queue.splice(0, slice.length);
      this.start(this.loadBatch(slice));
    }
  }

  private start(p: Promise<void>): void {
    this.active++;
    void p.finally(() => {
      this.active--;
      this.pump();
      this.afterBatch();
    });
  }

  private async loadBatch(hashes: string[]): Promise<void> {
    let batch: ChunkBatch;
    this.requests++;
    try {
      batch = await this.source.chunkBatch(hashes);
    } catch (e) {
      // A server that stayed busy (or out of reach) past the reads' patience is asked
      // again the next time a picture is wanted; any other refusal is final.
      const transient = e instanceof ApiError && (BUSY.has(e.status) || e.status === 0);
      for (const h of hashes) {
        if (transient) this.requested.delete(h);
        else this.fail(h);
      }
      return;
    }
    for (const h of batch.missing) this.fail(h);
    const done: string[] = [];
    for (const c of batch.contents) {
      try {
        this.store(c.hash, this.decode(c));
        done.push(c.hash);
      } catch {
        this.fail(c.hash);
      }
    }
    // A hash asked for but neither returned nor listed missing would wait forever.
    const answered = new Set([...done, ...batch.missing]);
    for (const h of hashes) if (!answered.has(h) && !this.ready.has(h)) this.fail(h);
    if (done.length) this.onLoad(done);
  }

  private store(hash: string, img: ChunkImage): void {
    this.ready.set(hash, img);
    this.fetched++;
    while (this.ready.size > this.capacity) {
      const old = this.ready.keys().next().value!;
      this.ready.delete(old);
      this.requested.delete(old);
    }
  }

  private fail(hash: string): void {
    this.failed.add(hash);
  }
}

/** zlib grey levels -> a small canvas the tiles can draw scaled (synchronous, see inflate). */
export function decodeContent(c: ChunkContent): ChunkImage {
  const pixels = new ImageData(greyToRgba(inflate(c.zlib), c.width, c.height), c.width, c.height);
  const canvas = typeof OffscreenCanvas === "function" ? new OffscreenCanvas(c.width, c.height) : Object.assign(document.createElement("canvas"), { width: c.width, height: c.height });
  (canvas.getContext("2d") as CanvasRenderingContext2D | OffscreenCanvasRenderingContext2D).putImageData(pixels, 0, 0);
  return canvas;
}
