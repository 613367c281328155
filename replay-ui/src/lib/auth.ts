/**
 * The API token this browser holds, kept in localStorage and sent only to this origin's
 * API: a writer token for the /controller page's REST writes, and a reader (or writer)
 * token for every read where the service asks for one (MAPSERVICE_API_READ_ACCESS=token).
 * Browsers cannot set headers on a WebSocket, so /api/v1/live gets it as a subprotocol.
 */
const KEY = "mapservice.apiToken";

export function apiToken(): string {
  try {
    return globalThis.localStorage?.getItem(KEY) ?? "";
  } catch {
    return ""; // storage disabled: no token
  }
}

export function setApiToken(token: string): void {
  try {
    const t = token.trim();
    if (t) globalThis.localStorage?.setItem(KEY, t);
    else globalThis.localStorage?.removeItem(KEY);
  } catch {
    /* storage disabled: the token lasts as long as the page */
  }
}

export function authHeaders(): Record<string, string> {
  const t = apiToken();
  return t ? { Authorization: `Bearer ${t}` } : {};
}

/** Subprotocols for /api/v1/live: the server accepts `mapservice.live`, the token rides along. */
export function liveProtocols(): string[] | undefined {
  const t = apiToken();
  return t ? ["mapservice.live", `bearer.${t}`] : undefined;
}
