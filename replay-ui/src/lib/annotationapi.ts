/**
 * The annotation endpoints as the replay uses them: the annotations standing at an instant,
 * their edits and the zone violations over a window, and an operator's edits. Every refusal
 * is an ApiError carrying the server's own message (why, and what to do), from `send`
 * (lib/request.ts), the writes' one request.
 */
import { getJson } from "./api";
import { send } from "./request";
import { bodyOf, type Annotation, type AnnotationDoc, type AnnotationEdit, type ZoneViolation } from "./annotations";

export { send } from "./request";

/** At most this many violations per window: a robot parked in a zone reports every second. */
export const VIOLATION_LIMIT = 5_000;

export interface Window<T> {
  items: T[];
  truncated: boolean;
}

export class AnnotationApi {
  constructor(public base = "") {}

  async at(atMs: number): Promise<Annotation[]> {
    const r = await getJson<{ annotations: Annotation[] }>(`${this.base}/api/v1/annotations?at=${Math.round(atMs)}`, "the zones");
    return r.annotations;
  }

  async edits(fromMs: number, toMs: number): Promise<Window<AnnotationEdit>> {
    const r = await getJson<{ edits: AnnotationEdit[]; truncated: boolean }>(
      `${this.base}/api/v1/annotations/edits?from=${Math.round(fromMs)}&to=${Math.round(toMs)}`, "the zone edits");
    return { items: r.edits, truncated: r.truncated };
  }

  async violations(fromMs: number, toMs: number): Promise<Window<ZoneViolation>> {
    const r = await getJson<{ violations: ZoneViolation[]; truncated: boolean }>(
      `${this.base}/api/v1/zone-violations?from=${Math.round(fromMs)}&to=${Math.round(toMs)}&limit=${VIOLATION_LIMIT}`, "the zone violations");
    return { items: r.violations, truncated: r.truncated };
  }

  /** The scopes of the token this browser holds (GET /api/v1/caller); [] when it cannot tell. */
  async scopes(): Promise<string[]> {
    try {
      return (await getJson<{ scopes: string[] }>(`${this.base}/api/v1/caller`, "what your token may do")).scopes;
    } catch {
      return [];
    }
  }

  create(doc: AnnotationDoc): Promise<Annotation | null> {
    return send<Annotation>("POST", `${this.base}/api/v1/annotations`, bodyOf(doc));
  }

  change(id: string, doc: AnnotationDoc): Promise<Annotation | null> {
    return send<Annotation>("PUT", `${this.base}/api/v1/annotations/${encodeURIComponent(id)}`, bodyOf(doc));
  }

  async remove(id: string): Promise<void> {
    await send<null>("DELETE", `${this.base}/api/v1/annotations/${encodeURIComponent(id)}`);
  }
}
