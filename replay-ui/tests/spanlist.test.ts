import { afterEach, beforeEach, describe, expect, it, vi } from "vitest";
import { effectScope, nextTick, ref } from "vue";
import { RELOAD_DELAY_MS, useSpanList, type SpanPage } from "../src/composables/useSpanList";

type Asked = { from: number; to: number; cursor: string | null; resolve: (p: SpanPage<number, string>) => void; reject: (e: Error) => void };

/** The composable over a reactive span and filter, its reads held until answered. */
function setUp(loadingAtOnce = false) {
  const span = ref<[number, number]>([0, 100_000]);
  const filter = ref("all");
  const asked: Asked[] = [];
  const scope = effectScope();
  const list = scope.run(() => useSpanList<number, string>({
    span: () => span.value,
    filterKey: () => filter.value,
    fetchPage: (from, to, cursor) => new Promise((resolve, reject) => asked.push({ from, to, cursor, resolve, reject })),
    loadingAtOnce,
  }))!;
  return { span, filter, asked, list, scope };
}

async function settle() {
  await nextTick();
  await Promise.resolve();
  await Promise.resolve();
}

describe("a list of the timeline's span", () => {
  beforeEach(() => vi.useFakeTimers());
  afterEach(() => vi.useRealTimers());

  it("reads the span once the span rests, and again only when it moved 2 % or the filter changed", async () => {
    const { span, filter, asked, list, scope } = setUp();
    expect(list.loading.value).toBe(true);
    vi.advanceTimersByTime(RELOAD_DELAY_MS - 1);
    expect(asked).toHaveLength(0);
    vi.advanceTimersByTime(1);
    expect(asked.map((a) => [a.from, a.to, a.cursor])).toEqual([[0, 100_000, null]]);
    asked[0].resolve({ items: [3, 2], next: "c1", info: "rule" });
    await settle();
    expect([list.items.value, list.next.value, list.info.value, list.loading.value]).toEqual([[3, 2], "c1", "rule", false]);

    span.value = [1_000, 101_000]; // 1 % of the span: kept
    await settle();
    vi.advanceTimersByTime(RELOAD_DELAY_MS);
    expect(asked).toHaveLength(1);
    span.value = [2_000, 102_000];
    await settle();
    vi.advanceTimersByTime(RELOAD_DELAY_MS);
    expect(asked.map((a) => a.from)).toEqual([0, 2_000]);
    filter.value = "r1";
    await settle();
    vi.advanceTimersByTime(RELOAD_DELAY_MS);
    expect(asked).toHaveLength(3);
    scope.stop();
  });

  it("appends the next page after the last cursor, and keeps the newest request's answer only", async () => {
    const { span, asked, list, scope } = setUp();
    vi.advanceTimersByTime(RELOAD_DELAY_MS);
    asked[0].resolve({ items: [9, 8], next: "c1", info: "" });
    await settle();
    void list.load(true);
    expect(asked[1].cursor).toBe("c1");
    asked[1].resolve({ items: [7], next: null, info: "" });
    await settle();
    expect([list.items.value, list.next.value]).toEqual([[9, 8, 7], null]);

    span.value = [50_000, 150_000];
    await settle();
    vi.advanceTimersByTime(RELOAD_DELAY_MS);
    span.value = [90_000, 190_000];
    await settle();
    vi.advanceTimersByTime(RELOAD_DELAY_MS);
    asked[3].resolve({ items: [1], next: null, info: "" });
    asked[2].resolve({ items: [5], next: null, info: "" }); // older request, answered late
    await settle();
    expect(list.items.value).toEqual([1]);
    scope.stop();
  });

  it("shows an error and keeps the list; a later answer clears it", async () => {
    const { list, asked, scope } = setUp();
    vi.advanceTimersByTime(RELOAD_DELAY_MS);
    asked[0].resolve({ items: [4], next: null, info: "" });
    await settle();
    void list.load();
    asked[1].reject(new Error("HTTP 503: try again"));
    await settle();
    expect([list.error.value, list.items.value, list.loading.value]).toEqual(["HTTP 503: try again", [4], false]);
    void list.load();
    asked[2].resolve({ items: [6], next: null, info: "" });
    await settle();
    expect([list.error.value, list.items.value]).toEqual([null, [6]]);
    scope.stop();
  });

  it("says loading as soon as a reload is due when asked to", async () => {
    for (const atOnce of [true, false]) {
      const { filter, asked, list, scope } = setUp(atOnce);
      vi.advanceTimersByTime(RELOAD_DELAY_MS);
      asked[0].resolve({ items: [], next: null, info: "" });
      await settle();
      filter.value = "r2";
      await settle();
      expect(list.loading.value).toBe(atOnce);
      scope.stop();
      vi.advanceTimersByTime(RELOAD_DELAY_MS);
      expect(asked).toHaveLength(1); // a stopped list asks nothing more
    }
  });
});
