/**
 * How the page asks the API: every read names this tab (SESSION_HEADER: the server serves
 * the tabs of one address in turns instead of refusing the second one), waits and asks
 * again when the server says it is busy (429/503: after Retry-After, else a growing,
 * jittered pause), shares one request among identical reads in flight, and stops asking
 * once nobody wants the answer any more (an AbortSignal). What went wrong is told in words
 * a user can act on, never as a status line or a setting's name.
 */
import { authHeaders } from "./auth";
import { backoffDelay } from "./live";

export const SESSION_HEADER = "X-Mapservice-Session";
/** This tab's name for the server's turns (api/admission.py); new with every page load. */
export const SESSION_ID = Math.random().toString(36).slice(2, 12);

/** The headers of every request of this page: its token (if any) and its session. */
export function pageHeaders(extra: Record<string, string> = {}): Record<string, string> {
  return { ...authHeaders(), [SESSION_HEADER]: SESSION_ID, ...extra };
}

/** Answers that say "busy, come back": the server's queues and per-caller shares. */
export const BUSY = new Set([429, 503]);
/** A busy server is asked again for this long at most; then the refusal is the answer. */
export const PATIENCE_MS = 120_000;
/** The longest pause before asking again, whatever Retry-After says. */
export const RETRY_CAP_MS = 30_000;

/** The pause before asking again after `failures` busy answers (0: the first): the
 * server's Retry-After if it gave one (seconds or an HTTP date), else the live stream's
 * jittered doubling backoff; at most RETRY_CAP_MS. */
export function retryDelayMs(failures: number, retryAfter: string | null, now = Date.now(), random = Math.random): number {
  let ms: number | null = null;
  if (retryAfter !== null && retryAfter.trim() !== "") {
    const seconds = Number(retryAfter);
    if (Number.isFinite(seconds)) ms = Math.max(0, seconds * 1000);
    else {
      const at = Date.parse(retryAfter);
      if (Number.isFinite(at)) ms = Math.max(0, at - now);
    }
  }
  // A little jitter on top of Retry-After too: tabs refused together do not return together.
  const ownMs = backoffDelay(failures, random);
  return Math.min(RETRY_CAP_MS, ms === null ? ownMs : ms + Math.round(250 * random()));
}

/** Who is waiting for a busy server now, for the page's status line. */
export const busyWaits = { count: 0, untilMs: 0 };

export interface FetchOptions {
  sleep?: (ms: number, signal?: AbortSignal) => Promise<void>;
  fetchFn?: typeof fetch;
  now?: () => number;
  random?: () => number;
}

export function abortableSleep(ms: number, signal?: AbortSignal): Promise<void> {
  return new Promise((resolve, reject) => {
    if (signal?.aborted) return reject(signal.reason);
    const timer = setTimeout(() => {
      signal?.removeEventListener("abort", onAbort);
      resolve();
    }, ms);
    const onAbort = () => {
      clearTimeout(timer);
      reject(signal?.reason);
    };
    signal?.addEventListener("abort", onAbort, { once: true });
  });
}

/** fetch with the page's headers, asked again while the server is busy (or unreachable:
 * it restarts) for up to PATIENCE_MS, then the last answer (or error). An abort ends it at
 * once, the wait included. */
export async function fetchRetrying(url: string, init: RequestInit = {}, opts: FetchOptions = {}): Promise<Response> {
  const sleep = opts.sleep ?? abortableSleep;
  const fetchFn = opts.fetchFn ?? ((u: string, i?: RequestInit) => fetch(u, i));
  const now = opts.now ?? Date.now;
  const random = opts.random ?? Math.random;
  const giveUpAt = now() + PATIENCE_MS;
  const headers = pageHeaders((init.headers ?? {}) as Record<string, string>);
  for (let failures = 0; ; failures++) {
    let answer: Response | null = null;
    let failure: unknown = null;
    try {
      answer = await fetchFn(url, { ...init, headers });
      if (!BUSY.has(answer.status)) return answer;
    } catch (e) {
      if (init.signal?.aborted) throw e;
      failure = e;
    }
    const wait = retryDelayMs(failures, answer?.headers.get("Retry-After") ?? null, now(), random);
    if (now() + wait > giveUpAt) {
      if (answer) return answer;
      throw failure;
    }
    await answer?.body?.cancel().catch(() => undefined);
    busyWaits.count++;
    busyWaits.untilMs = Math.max(busyWaits.untilMs, now() + wait);
    try {
      await sleep(wait, init.signal ?? undefined);
    } finally {
      busyWaits.count--;
    }
  }
}

export class ApiError extends Error {
  constructor(public status: number, message: string, public detail = "") {
    super(message);
  }
}

/** What a user should read when a read of `what` failed with `status`: what happened and
 * what to do. `detail` (the server's own words, for whoever runs it) is kept apart. */
export function explainFailure(what: string, status: number): string {
  if (status === 401 || status === 403) {
    return `Loading ${what} needs an API token this page does not have: enter a reader token in the API token field (your administrator has one).`;
  }
  if (BUSY.has(status)) {
    return `The server stayed too busy to load ${what} for two minutes. The page keeps what it shows; try again in a minute, or tell whoever runs the service that it is overloaded.`;
  }
  if (status === 404) return `The server does not know ${what}: the page may be older than the server. Reload the page.`;
  if (status === 400 || status === 422) return `The server refused to load ${what} for this view. Pick another time or span, or reload the page.`;
  if (status >= 500) return `The server failed while loading ${what}. Try again in a moment; if it keeps failing, tell whoever runs the service.`;
  return `Loading ${what} failed (HTTP ${status}). Reload the page; if it keeps failing, tell whoever runs the service.`;
}

/** The words for a read that never got an answer (network down, server restarting). */
export function explainUnreachable(what: string): string {
  return `The server could not be reached to load ${what} for two minutes. Check the network; the page asks again when you move the playhead.`;
}

/** An error's text for the page (an ApiError's message is already meant for it). */
export function errorText(e: unknown): string {
  if (e instanceof ApiError) return e.message;
  if (e instanceof Error) return e.message;
  return String(e);
}

/** One read in flight per URL: the callers of the same read share one request, each may
 * give up on its own (its signal), and the request is cancelled once all of them did. */
interface Shared {
  answer: Promise<{ status: number; text: string; headers: Headers }>;
  controller: AbortController;
  users: number;
}

const inFlight = new Map<string, Shared>();

/** How many reads are shared now (for tests). */
export function sharedInFlight(): number {
  return inFlight.size;
}

function abortError(signal: AbortSignal): unknown {
  return signal.reason ?? new DOMException("The read was cancelled", "AbortError");
}

/** GET `url` (retried while busy), its status and body text, shared with identical reads in
 * flight; rejects when `signal` aborts (the request itself stops once no one wants it). */
export function sharedGet(
  url: string, signal?: AbortSignal, opts: FetchOptions = {},
): Promise<{ status: number; text: string; headers: Headers }> {
  if (signal?.aborted) return Promise.reject(abortError(signal));
  let shared = inFlight.get(url);
  if (!shared) {
    const controller = new AbortController();
    const answer = fetchRetrying(url, { signal: controller.signal }, opts)
      .then(async (r) => ({ status: r.status, text: await r.text(), headers: r.headers }));
    const entry: Shared = { answer, controller, users: 0 };
    shared = entry;
    inFlight.set(url, entry);
    const forget = () => { if (inFlight.get(url) === entry) inFlight.delete(url); };
    answer.then(forget, forget);
  }
  const entry = shared;
  entry.users++;
  return new Promise((resolve, reject) => {
    let done = false;
    const leave = () => {
      if (done) return;
      done = true;
      entry.users--;
      signal?.removeEventListener("abort", onAbort);
    };
    const onAbort = () => {
      leave();
      if (entry.users === 0) {
        if (inFlight.get(url) === entry) inFlight.delete(url);
        entry.controller.abort();
      }
      reject(abortError(signal!));
    };
    signal?.addEventListener("abort", onAbort, { once: true });
    entry.answer.then((a) => { if (!done) { leave(); resolve(a); } }, (e) => { if (!done) { leave(); reject(e); } });
  });
}

/** Whether `e` is the end of a read nobody wants any more (not a failure to show). */
export function isAbort(e: unknown): boolean {
  return (e instanceof DOMException || e instanceof Error) && e.name === "AbortError";
}

/** GET `url` as JSON: shared with the same read in flight, asked again while the server
 * is busy, given up when `signal` aborts. A failure is an ApiError whose message says, in
 * a user's words, what of `what` could not be loaded and what to do (the server's own
 * words are its `detail`). */
export async function getJson<T>(url: string, what = "the data", signal?: AbortSignal): Promise<T> {
  let answer;
  try {
    answer = await sharedGet(url, signal);
  } catch (e) {
    if (isAbort(e) || signal?.aborted) throw e;
    throw new ApiError(0, explainUnreachable(what), String(e));
  }
  if (answer.status < 200 || answer.status > 299) {
    let detail = "";
    try {
      const d = JSON.parse(answer.text).detail;
      detail = typeof d === "string" ? d : JSON.stringify(d);
    } catch {
      /* not JSON */
    }
    throw new ApiError(answer.status, explainFailure(what, answer.status), detail);
  }
  return JSON.parse(answer.text) as T;
}

/** GET `url`'s bytes (a picture), asked again while the server is busy; a failure is an
 * ApiError in a user's words about `what`, as getJson's. */
export async function getBlob(url: string, what: string, signal?: AbortSignal): Promise<Blob> {
  return (await getBlobAnswer(url, what, signal)).blob;
}

/** `getBlob`'s body with the answer's headers (what the body alone does not say). */
export async function getBlobAnswer(url: string, what: string, signal?: AbortSignal): Promise<{ blob: Blob; headers: Headers }> {
  let r: Response;
  try {
    r = await fetchRetrying(url, { signal });
  } catch (e) {
    if (isAbort(e) || signal?.aborted) throw e;
    throw new ApiError(0, explainUnreachable(what), String(e));
  }
  if (!r.ok) throw new ApiError(r.status, explainFailure(what, r.status), await r.text().catch(() => ""));
  return { blob: await r.blob(), headers: r.headers };
}

/** One read of a kind at a time: asking again cancels the read before, whose answer would
 * be stale (a picture of the floor superseded by a newer one). */
export class Superseding {
  private current: AbortController | null = null;

  /** The signal of the new read; the previous read's is aborted. */
  next(): AbortSignal {
    this.current?.abort();
    this.current = new AbortController();
    return this.current.signal;
  }

  cancel(): void {
    this.current?.abort();
    this.current = null;
  }
}

/** A write (`method` with a JSON `body`) through the page's request layer, the answer's JSON
 * (null for 204); a refusal is an ApiError carrying the server's own words (why, and what to
 * do), as `<status>: <detail>`. */
export async function send<T>(method: string, url: string, body?: unknown): Promise<T | null> {
  const r = await fetchRetrying(url, {
    method,
    headers: body === undefined ? {} : { "Content-Type": "application/json" },
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (!r.ok) {
    let detail: unknown = r.statusText;
    try {
      detail = (await r.json()).detail ?? detail;
    } catch {
      /* not JSON */
    }
    const text = typeof detail === "string" ? detail
      : Array.isArray(detail) ? detail.map((d) => `${(d.loc ?? []).slice(1).join(".")}: ${d.msg}`).join("; ")
      : JSON.stringify(detail);
    throw new ApiError(r.status, `${r.status}: ${text}`);
  }
  return r.status === 204 ? null : ((await r.json()) as T);
}
