/**
 * Chunk pictures by content hash: each distinct hash is fetched once (the API marks them
 * immutable, so the browser cache also keeps them across reloads), decoded once, and kept
 * in a bounded LRU of decoded bitmaps.
 */

export type ChunkImage = ImageBitmap | HTMLImageElement;

export class ChunkImages {
  private ready = new Map<string, ChunkImage>();
  private requested = new Set<string>();
  private queue: string[] = [];
  private active = 0;
  /** Downloads done (each distinct hash once). */
  fetched = 0;
  failed = new Set<string>();
  onLoad: (hash: string) => void = () => {};

  constructor(private url: (hash: string) => string, public concurrency = 8, public capacity = 6000) {}

  get(hash: string): ChunkImage | undefined {
    const img = this.ready.get(hash);
    if (img) {
      this.ready.delete(hash); // refresh its place in the LRU
      this.ready.set(hash, img);
    }
    return img;
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
    this.pump();
  }

  get queued(): number {
    return this.queue.length + this.active;
  }

  private pump(): void {
    while (this.active < this.concurrency && this.queue.length) {
      const hash = this.queue.shift()!;
      this.active++;
      this.load(hash)
        .then((img) => {
          this.ready.set(hash, img);
          this.fetched++;
          while (this.ready.size > this.capacity) {
            const old = this.ready.keys().next().value!;
            this.ready.delete(old);
            this.requested.delete(old);
          }
          this.onLoad(hash);
        })
        .catch(() => this.failed.add(hash))
        .finally(() => {
          this.active--;
          this.pump();
        });
    }
  }

  private async load(hash: string): Promise<ChunkImage> {
    const r = await fetch(this.url(hash));
    if (!r.ok) throw new Error(`${r.status}`);
    const blob = await r.blob();
    if (typeof createImageBitmap === "function") return createImageBitmap(blob);
    const img = new Image();
    img.src = URL.createObjectURL(blob);
    await img.decode();
    return img;
  }
}
