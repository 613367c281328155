/**
 * The API's live WebSocket with automatic reconnect (1 s doubling to 10 s) and latency:
 * the time from a robot's event to this page (clock skew included) and from the server's
 * send to this page.
 */
import type { ChunkChange, Pose } from "./types";

export type LiveMessage =
  | ({ type: "pose"; sent_ms?: number } & Pose)
  | ({ type: "chunk"; sent_ms?: number; receive_time_ms?: number } & ChunkChange);

export interface LiveStatus {
  connected: boolean;
  latencyMs: number | null; // event time -> shown (smoothed)
  messages: number;
  reconnects: number;
}

export class LiveConnection {
  status: LiveStatus = { connected: false, latencyMs: null, messages: 0, reconnects: 0 };
  private ws: WebSocket | null = null;
  private stopped = true;
  private backoff = 1000;
  private timer: ReturnType<typeof setTimeout> | null = null;

  constructor(
    private url: string,
    private onMessage: (m: LiveMessage) => void,
    private onOpen: (reconnect: boolean) => void,
  ) {}

  start(): void {
    this.stopped = false;
    this.connect(false);
  }

  stop(): void {
    this.stopped = true;
    if (this.timer) clearTimeout(this.timer);
    this.ws?.close();
    this.ws = null;
    this.status.connected = false;
  }

  private connect(reconnect: boolean): void {
    const ws = new WebSocket(this.url);
    this.ws = ws;
    ws.onopen = () => {
      this.backoff = 1000;
      this.status.connected = true;
      this.onOpen(reconnect);
    };
    ws.onmessage = (e) => {
      const m = JSON.parse(e.data) as LiveMessage;
      this.status.messages++;
      const lag = Date.now() - m.ts_ms;
      this.status.latencyMs = this.status.latencyMs === null ? lag : Math.round(0.8 * this.status.latencyMs + 0.2 * lag);
      this.onMessage(m);
    };
    ws.onclose = () => {
      this.status.connected = false;
      if (this.ws !== ws || this.stopped) return;
      this.status.reconnects++;
      this.timer = setTimeout(() => this.connect(true), this.backoff);
      this.backoff = Math.min(10_000, this.backoff * 2);
    };
  }
}

export function liveUrl(loc: Location): string {
  return `${loc.protocol === "https:" ? "wss" : "ws"}://${loc.host}/api/v1/live`;
}
