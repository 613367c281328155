import { afterEach, describe, expect, it, vi } from "vitest";
import { nextTick, ref, shallowRef } from "vue";
import { useHeatmap } from "../src/composables/useHeatmap";
import type { MapView } from "../src/lib/mapview";
import { parseUrlState } from "../src/lib/urlstate";

const GRID = { kind: "occupancy", unit: "robot-seconds", from_ms: 0, to_ms: 1, cell_m: 0.5, max: 3, total: 4,
  box: { i0: 2, j0: -1, columns: 3, rows: 2 }, cells: [[2, -1, 1], [4, 0, 3]] };

/** fetch as the API answers the heatmap's read (a PNG with the grid's summary in a
 * header; a picture without it when `headerless`); every URL asked is kept. */
function api(headerless = false) {
  const asked: URL[] = [];
  vi.stubGlobal("fetch", async (url: string) => {
    const u = new URL(url, "http://x");
    asked.push(u);
    const grid = { ...GRID, kind: u.searchParams.get("kind"), cell_m: Number(u.searchParams.get("cell")) };
    const headers: Record<string, string> = headerless ? {} : { "X-Heatmap-Summary": JSON.stringify(grid) };
    return new Response(new Blob([new Uint8Array([137, 80, 78, 71])]), { status: 200, headers });
  });
  vi.stubGlobal("URL", Object.assign(URL, { createObjectURL: () => "blob:heat", revokeObjectURL: () => {} }));
  return asked;
}

/** A map that records what it was asked to show. */
function fakeView(hasFloor: () => boolean) {
  const shown: unknown[] = [];
  const view = {
    map: { on: () => {} },
    metresPerScreenPixel: () => 0.05,
    showHeatmap: (url: string | null, box: unknown) => {
      if (url && !hasFloor()) return false;
      shown.push(url ? { url, box } : null);
      return true;
    },
  };
  return { view: shallowRef(view as unknown as MapView), shown };
}

async function settle(ms = 0) {
  await new Promise((r) => setTimeout(r, ms));
  for (let i = 0; i < 5; i++) await new Promise((r) => setTimeout(r, 0));
  await nextTick();
}

afterEach(() => vi.unstubAllGlobals());

describe("the heatmap layer", () => {
  it("reads a linked heatmap at once and lays it over its box in metres once the map has a floor", async () => {
    const asked = api();
    let floor = false;
    const { view, shown } = fakeView(() => floor);
    const h = useHeatmap({ base: "", view, initial: parseUrlState("?heat=occupancy,2"), span: () => [1000, 3_601_000] });
    await settle();
    expect(asked.map((u) => [u.searchParams.get("kind"), u.searchParams.get("cell"), u.searchParams.get("format")]))
      .toEqual([["occupancy", "2", "png"]]); // one request: the legend's summary is its header
    expect(h.grid.value?.kind).toBe("occupancy");
    expect(shown).toEqual([]);
    floor = true;
    await settle(250);
    expect(shown).toEqual([{ url: "blob:heat", box: { x0: 4, y0: -2, x1: 10, y1: 2 } }]);
    expect(h.bar.value).toEqual({ metres: 5, px: 100, label: "5 m" });
  });

  it("reads again when its kind, cell or span changes, not for a span moved by less than 2 %", async () => {
    const asked = api();
    const { view, shown } = fakeView(() => true);
    const span = ref<[number, number]>([0, 100_000]);
    const h = useHeatmap({ base: "", view, initial: parseUrlState(""), span: () => span.value });
    await settle();
    expect(asked).toEqual([]); // off: nothing read
    h.on.value = true;
    await settle();
    expect(asked.length).toBe(1);
    span.value = [1000, 101_000]; // 1 %
    await settle(350);
    expect(asked.length).toBe(1);
    span.value = [5000, 105_000]; // 5 %
    await settle(350);
    expect(asked.length).toBe(2);
    h.choice.value = { kind: "speed", cell: 1 };
    await settle(350);
    expect(asked.slice(-1).map((u) => [u.searchParams.get("kind"), u.searchParams.get("cell")])).toEqual([["speed", "1"]]);
    expect(h.state.value).toEqual({ kind: "speed", cell: 1 });
    // Off: the picture goes, nothing more is read.
    h.on.value = false;
    await settle(350);
    expect(shown.at(-1)).toBeNull();
    expect(h.state.value).toBeNull();
    span.value = [50_000, 150_000];
    await settle(350);
    expect(asked.length).toBe(3);
  });

  it("says what to do when the picture comes without its summary (a server older than the page)", async () => {
    api(true);
    const { view, shown } = fakeView(() => true);
    const h = useHeatmap({ base: "", view, initial: parseUrlState("?heat=dwell"), span: () => [0, 100_000] });
    await settle();
    expect(h.error.value).toMatch(/X-Heatmap-Summary.*reload the page/);
    expect(h.grid.value).toBeNull();
    expect(shown).toEqual([]);
  });
});
