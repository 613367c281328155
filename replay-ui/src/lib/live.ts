/**
 * The API's live WebSocket with automatic reconnect and latency: the time from a robot's
 * event to this page (clock skew included) and from the server's send to this page.
 * Events come in batched frames (a JSON array each); a single object is still understood.
 *
 * Reconnects back off exponentially with jitter (1 s doubling to 30 s, each wait drawn
 * from its upper half), and the backoff resets only once a connection proved itself
 * (a message, or STABLE_MS open): a server that accepts and closes at once (1013 while
 * its live feed starts, 1011 without one) is retried less and less often, so tabs
 * neither hammer it nor re-seek the replay once a second, and many tabs spread out.
 */
import type { ChunkChange, Pose } from "./types";
import type { IncidentAnnouncement } from "./incidents";
import { liveProtocols } from "./auth";

export type LiveMessage =
  | ({ type: "pose"; sent_ms?: number } & Pose)
  | ({ type: "chunk"; sent_ms?: number; receive_time_ms?: number } & ChunkChange)
  | IncidentAnnouncement;

export interface LiveStatus {
  connected: boolean;
  latencyMs: number | null; // event time -> shown (smoothed)
  messages: number;
  reconnects: number;
  /** Connections opened so far: a list kept current by the stream knows its own. */
  connections: number;
}

export const BACKOFF_BASE_MS = 1000;
export const BACKOFF_CAP_MS = 30_000;
export const STABLE_MS = 10_000;

/** The wait before reconnect attempt `failures` (0 = the first after a good connection):
 * min(cap, base * 2^failures), scaled into its upper half by `random()` in [0, 1). */
export function backoffDelay(failures: number, random: () => number = Math.random): number {
  const ceiling = Math.min(BACKOFF_CAP_MS, BACKOFF_BASE_MS * 2 ** Math.min(failures, 30));
  return Math.round(ceiling / 2 + (ceiling / 2) * random());
}

export class LiveConnection {
  status: LiveStatus = { connected: false, latencyMs: null, messages: 0, reconnects: 0, connections: 0 };
  private ws: WebSocket | null = null;
  private stopped = true;
  private failures = 0; // reconnects since the last connection that proved itself
  private timer: ReturnType<typeof setTimeout> | null = null;
  private stableTimer: ReturnType<typeof setTimeout> | null = null;

  constructor(
    private url: string,
    private onMessage: (m: LiveMessage) => void,
    private onOpen: (reconnect: boolean) => void,
    private random: () => number = Math.random,
  ) {}

  start(): void {
    this.stopped = false;
    this.connect(false);
  }

  stop(): void {
    this.stopped = true;
    if (this.timer) clearTimeout(this.timer);
    if (this.stableTimer) clearTimeout(this.stableTimer);
    this.ws?.close();
    this.ws = null;
    this.status.connected = false;
  }

  private connect(reconnect: boolean): void {
    const ws = new WebSocket(this.url, liveProtocols());
    this.ws = ws;
    ws.onopen = () => {
      this.status.connected = true;
      this.status.connections++;
      this.stableTimer = setTimeout(() => (this.failures = 0), STABLE_MS);
      this.onOpen(reconnect);
    };
    ws.onmessage = (e) => {
      this.failures = 0;
      const data = JSON.parse(e.data) as LiveMessage | LiveMessage[];
      // A batch (we ask for ?batch=true) or one event (servers from before batching).
      const events = Array.isArray(data) ? data : [data];
      if (events.length === 0) return;
      this.status.messages += events.length;
      // One latency sample per frame, from its newest robot event (an incident's time is
      // when it was found, not a robot's): the smoothing stays per arrival rather than
      // being swamped by a catch-up frame of a thousand old events.
      const newest = [...events].reverse().find((m) => m.type !== "incident");
      if (newest) {
        const lag = Date.now() - newest.ts_ms;
        this.status.latencyMs = this.status.latencyMs === null ? lag : Math.round(0.8 * this.status.latencyMs + 0.2 * lag);
      }
      for (const m of events) this.onMessage(m);
    };
    ws.onclose = () => {
      this.status.connected = false;
      if (this.stableTimer) clearTimeout(this.stableTimer);
      if (this.ws !== ws || this.stopped) return;
      this.status.reconnects++;
      this.timer = setTimeout(() => this.connect(true), backoffDelay(this.failures, this.random));
      this.failures++;
    };
  }
}

/** The live stream of the page's own server, in batched frames: at thousands of events
 * a second one message (and one onmessage) per batch rather than per event. */
export function liveUrl(loc: Pick<Location, "protocol" | "host">): string {
  return `${loc.protocol === "https:" ? "wss" : "ws"}://${loc.host}/api/v1/live?batch=true`;
}
