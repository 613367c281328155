import { afterEach, beforeEach, describe, expect, it, vi } from "vitest";
import { effectScope, nextTick, ref } from "vue";
import { ApiError } from "../src/lib/api";
import { RETENTION_MS } from "../src/lib/retention";
import type { TrackBuckets } from "../src/lib/types";
import { initialSpan, shownSpan } from "../src/lib/timeline";
import { parseUrlState } from "../src/lib/urlstate";
import { READ_DELAY_MS, REFRESH_MS, RETRY_FIRST_MS, RETRY_MAX_MS, usePlotReads } from "../src/composables/usePlotReads";

const NOW = Date.UTC(2026, 10, 26, 12, 0, 0);
const HOUR = 3_600_000;
const iso = (ms: number) => new Date(ms).toISOString();

type Asked = { id: string; from: number; to: number; buckets: number; resolve: (t: TrackBuckets) => void; reject: (e: Error) => void };

/** The oldest instant App.vue gives the plots: the retention back from the present, a minute's margin. */
const appOldest = () => Date.now() - RETENTION_MS + 60_000;

/**
 * The plot panel's reads wired as the page wires them: the span is the timeline strip's
 * once it is mounted, before that what App.vue gives the panels (shownSpan), from the
 * address; the oldest instant readable is App.vue's unless given; the panel reads once at
 * its mount (PlotPanel's onMounted), its reads held until answered.
 */
function page(search: string, robots = ["r1"], oldestMs = appOldest) {
  const initial = parseUrlState(search);
  const strip = ref<{ viewFrom: number; viewTo: number } | null>(null);
  const asked: Asked[] = [];
  const scope = effectScope();
  const plots = scope.run(() => usePlotReads({
    read: (id, from, to, buckets) => new Promise((resolve, reject) => asked.push({ id, from, to, buckets, resolve, reject })),
    robots: () => robots,
    span: () => shownSpan(strip.value, initial.span, Date.now()),
    oldestMs,
    width: () => 800,
  }))!;
  void plots.load(); // the panel's mount, ahead of the strip's
  /** The strip mounted: it starts on the span it computes from the address. */
  const mountStrip = () => {
    const [viewFrom, viewTo] = initialSpan(initial.span, Date.now());
    strip.value = { viewFrom, viewTo };
  };
  return { asked, plots, strip, mountStrip, scope };
}

async function settle() {
  await nextTick();
  for (let i = 0; i < 5; i++) await Promise.resolve();
}

/** The API's answer to `a`: its first `n` buckets hold poses, a metre driven in each. */
function answer(n: number, a: Asked): TrackBuckets {
  const bucket_ms = Math.max(1000, Math.ceil((a.to - a.from) / (a.buckets - 1) / 1000) * 1000);
  const first = Math.floor(a.from / bucket_ms) * bucket_ms;
  const buckets = Array.from({ length: n }, (_, i) => {
    const start_ms = first + i * bucket_ms;
    return { start_ms, poses: 2, steps: 1, distance_m: 1, step_ms: 1000, speed_mps: 1, first_ms: Math.max(start_ms, a.from),
      last_ms: Math.max(start_ms, a.from) + 1, battery_min: 50, battery_max: 60, battery_mean: 55 };
  });
  return { robotId: a.id, from_ms: a.from, to_ms: a.to, bucket_ms, distance_m: n, buckets };
}
const driven = (plots: ReturnType<typeof usePlotReads>) =>
  plots.data.value.series.get("r1")?.distance.at(-1);

describe("the plot panel's reads", () => {
  beforeEach(() => {
    vi.useFakeTimers();
    vi.setSystemTime(NOW);
  });
  afterEach(() => vi.useRealTimers());

  it("reads the address's span first (not the last hour), once, and again when the span changes", async () => {
    const span = [NOW - 2 * 24 * HOUR, NOW - 24 * HOUR];
    const { asked, plots, strip, mountStrip, scope } = page(`?t=${NOW - 30 * HOUR}&span=${iso(span[0])},${iso(span[1])}`);
    expect(asked).toHaveLength(1);
    const first = asked[0];
    expect(first.to).toBe(span[1] + 1);
    expect(first.from).toBe(span[0]);
    first.resolve(answer(50, first));
    mountStrip();
    await settle();
    vi.advanceTimersByTime(READ_DELAY_MS);
    expect(asked).toHaveLength(1); // the strip shows the span read: nothing to read again
    expect(driven(plots)).toBe(50);

    strip.value = { viewFrom: span[0] + HOUR, viewTo: span[1] - HOUR }; // a zoom
    await settle();
    vi.advanceTimersByTime(READ_DELAY_MS);
    expect(asked).toHaveLength(2);
    expect(asked[1].to).toBe(span[1] - HOUR + 1);
    scope.stop();
  });

  it("without a span in the address, reads the hour the strip starts on", async () => {
    const { asked, mountStrip, scope } = page(`?t=${NOW - HOUR / 2}`);
    expect(asked.map((a) => a.to)).toEqual([NOW + 1]);
    expect(asked[0].from).toBe(NOW - HOUR);
    asked[0].resolve(answer(0, asked[0]));
    mountStrip();
    await settle();
    vi.advanceTimersByTime(READ_DELAY_MS);
    expect(asked).toHaveLength(1);
    scope.stop();
  });

  it("after a failed read says so, reads again after a backoff, and shows the data", async () => {
    const span = [NOW - 2 * 24 * HOUR, NOW - 24 * HOUR];
    const { asked, plots, scope } = page(`?span=${iso(span[0])},${iso(span[1])}`);
    asked[0].reject(new ApiError(503, "503 Service Unavailable"));
    await settle();
    expect(plots.error.value).toBe("plots not read (503 Service Unavailable): trying again in 1 s");
    expect(plots.loading.value).toBe(false);
    vi.advanceTimersByTime(RETRY_FIRST_MS - 1);
    expect(asked).toHaveLength(1);
    vi.advanceTimersByTime(1);
    expect(asked).toHaveLength(2);
    expect([asked[1].from, asked[1].to]).toEqual([asked[0].from, asked[0].to]);
    asked[1].resolve(answer(30, asked[1]));
    await settle();
    expect(plots.error.value).toBeNull();
    expect(driven(plots)).toBe(30);
    vi.advanceTimersByTime(10 * REFRESH_MS);
    expect(asked).toHaveLength(2); // a past span read is not read again
    scope.stop();
  });

  it("tries again ever later while reads fail, never more than RETRY_MAX_MS apart", async () => {
    const { asked, plots, scope } = page(`?span=${iso(NOW - 3 * HOUR)},${iso(NOW - 2 * HOUR)}`);
    const waits: number[] = [];
    for (let i = 0; i < 8; i++) {
      asked[i].reject(new Error("Failed to fetch"));
      await settle();
      let waited = 0;
      while (asked.length === i + 1 && waited <= RETRY_MAX_MS) {
        vi.advanceTimersByTime(1000);
        waited += 1000;
      }
      waits.push(waited);
    }
    expect(waits).toEqual([1000, 2000, 4000, 8000, 16000, RETRY_MAX_MS, RETRY_MAX_MS, RETRY_MAX_MS]);
    expect(plots.error.value).toContain("Failed to fetch");
    scope.stop();
  });

  it("reads a span reaching the present again as its poses arrive", async () => {
    const { asked, plots, scope } = page(`?span=${iso(NOW - 7 * 24 * HOUR)},${iso(NOW)}`);
    // The whole retention: within the one window the API reads.
    expect(asked[0].to - asked[0].from).toBeLessThanOrEqual(RETENTION_MS);
    expect(asked[0].from).toBeGreaterThanOrEqual(NOW - RETENTION_MS);
    asked[0].resolve(answer(3, asked[0])); // a history still being written
    await settle();
    expect(driven(plots)).toBe(3);
    vi.advanceTimersByTime(REFRESH_MS);
    expect(asked).toHaveLength(2);
    // The same span, from the oldest instant kept at this read (30 s later).
    expect([asked[1].from, asked[1].to]).toEqual([appOldest(), asked[0].to]);
    asked[1].resolve(answer(200, asked[1]));
    await settle();
    expect(driven(plots)).toBe(200);
    scope.stop();
  });

  it("reads a span older than the oldest instant it is given from that instant, as it is at each read", async () => {
    // Not the retention back from now: the reads take the page's oldest instant, not one of their own.
    let oldest = NOW - 2 * 24 * HOUR - 30 * 60_000;
    const { asked, scope } = page(`?span=${iso(NOW - 3 * 24 * HOUR)},${iso(NOW)}`, ["r1"], () => oldest);
    expect(asked[0].from).toBe(oldest);
    expect(asked[0].to).toBe(NOW + 1);
    asked[0].resolve(answer(0, asked[0]));
    await settle();
    oldest += HOUR;
    vi.advanceTimersByTime(REFRESH_MS); // the span reaches the present: read again
    expect(asked).toHaveLength(2);
    expect(asked[1].from).toBe(oldest);
    scope.stop();
  });

  it("reads a span ending in the future in one window of at most the retention", async () => {
    const { asked, scope } = page(`?span=${iso(NOW - 8 * 24 * HOUR)},${iso(NOW + 24 * HOUR)}`);
    expect(asked[0].to).toBe(NOW + 24 * HOUR + 1);
    expect(asked[0].to - asked[0].from).toBeLessThanOrEqual(RETENTION_MS);
    expect(asked[0].from).toBeGreaterThan(appOldest());
    scope.stop();
  });

  it("says why the API refused a read, and does not repeat it until the span changes", async () => {
    const { asked, plots, strip, mountStrip, scope } = page(`?span=${iso(NOW - 3 * HOUR)},${iso(NOW - 2 * HOUR)}`);
    asked[0].reject(new ApiError(400, "400 'from' is after 'to'"));
    mountStrip();
    await settle();
    expect(plots.error.value).toBe("plots not read (400 'from' is after 'to')");
    vi.advanceTimersByTime(10 * RETRY_MAX_MS);
    expect(asked).toHaveLength(1);
    strip.value = { viewFrom: NOW - 4 * HOUR, viewTo: NOW - 2 * HOUR };
    await settle();
    vi.advanceTimersByTime(READ_DELAY_MS);
    expect(asked).toHaveLength(2);
    scope.stop();
  });
});
