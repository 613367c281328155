import { afterEach, describe, expect, it, vi } from "vitest";
import { nextTick, shallowRef } from "vue";
import { useAnnotations } from "../src/composables/useAnnotations";
import type { Annotation } from "../src/lib/annotations";
import type { MapView } from "../src/lib/mapview";

const ZONE: Annotation = {
  id: "z1", annotation: { shape: "zone", name: "aisle", kind: "keep_out", polygon: [[0, 0], [4, 0], [4, 4]] },
  created_ms: 1, created_by: "operator:a", changed_ms: 1, changed_by: "operator:a",
};

/** The API as the page reads it: `store.zones` is what the store holds (it takes the
 * page's removal only when the test says so, as the history takes it a second later). */
function api(store: { zones: Annotation[] }) {
  const reads: number[] = [];
  vi.stubGlobal("fetch", async (url: string, init?: RequestInit) => {
    const u = new URL(url, "http://x");
    const json = (body: unknown, status = 200) => new Response(JSON.stringify(body), { status });
    if (init?.method === "DELETE") return new Response(null, { status: 204 });
    if (u.pathname === "/api/v1/caller") return json({ scopes: ["read", "operator"] });
    if (u.pathname === "/api/v1/annotations/edits") return json({ edits: [], truncated: false });
    if (u.pathname === "/api/v1/zone-violations") return json({ violations: [], truncated: false });
    if (u.pathname === "/api/v1/annotations") {
      reads.push(Number(u.searchParams.get("at")));
      return json({ annotations: store.zones });
    }
    return json({ detail: "not here" }, 404);
  });
  return reads;
}

async function settle(ms = 0) {
  await new Promise((r) => setTimeout(r, ms));
  for (let i = 0; i < 5; i++) await new Promise((r) => setTimeout(r, 0));
  await nextTick();
}

afterEach(() => {
  vi.unstubAllGlobals();
  vi.restoreAllMocks();
});

describe("the annotations at the playhead", () => {
  it("are read again until they show this page's edit, which the store holds a moment after the API took it", async () => {
    vi.spyOn(console, "warn").mockImplementation(() => {}); // its lifecycle hooks, outside a component
    const store = { zones: [ZONE] };
    const reads = api(store);
    const now = Date.now();
    const a = useAnnotations({
      base: "", view: shallowRef<MapView | null>(null), span: () => [now - 60_000, now + 60_000],
      seek: () => {}, live: () => false,
    });
    a.tick(now - 1_000);
    await settle();
    expect(a.list.map((z) => z.id)).toEqual(["z1"]);
    a.select("z1");
    a.remove();
    await settle();
    const after = Date.now() + 1_000;
    a.tick(after); // the edit is crossed: read again, before the store has the removal
    await settle();
    expect(reads.at(-1)).toBe(after);
    expect(a.list.map((z) => z.id)).toEqual(["z1"]);
    expect(a.hook().settled).toBe(false);
    store.zones = []; // the history has it now
    for (let i = 0; i < 8 && a.hook().settled === false; i++) {
      await settle(150);
      a.tick(after);
      await settle();
    }
    expect(a.list).toEqual([]);
    expect(a.hook().settled).toBe(true);
    const settledReads = reads.length;
    await settle(700);
    a.tick(after);
    await settle();
    expect(reads.length).toBe(settledReads); // shown: no more reads
  });
});
