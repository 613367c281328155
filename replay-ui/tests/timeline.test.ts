import { describe, expect, it } from "vitest";
import { BAR_MAX_PX, MIN_BAR_PX, barHeight, bucketAt, bucketText, estimateLabelPx, stripMarks, timeTicks } from "../src/lib/timeline";

const bucket = (start_ms: number, chunk_changes: number, conflicts: number, robots_active: number) =>
  ({ start_ms, chunk_changes, conflicts, robots_active });

describe("stripMarks", () => {
  const xOf = (t: number) => t / 10; // 10 ms a pixel
  const tl = {
    from_ms: 0, to_ms: 300, bucket_ms: 100,
    buckets: [bucket(0, 0, 0, 5), bucket(100, 4, 1, 2), bucket(200, 2, 0, 0)],
  };
  const marks = stripMarks(tl, xOf);

  it("bands every bucket where robots reported, map changes or not", () => {
    expect(marks.map((m) => m.active)).toEqual([true, true, false]);
  });

  it("scales change bars to the busiest bucket (square root, with a floor) and keeps the conflict counts", () => {
    expect(marks.map((m) => m.h)).toEqual([0, BAR_MAX_PX, MIN_BAR_PX + (BAR_MAX_PX - MIN_BAR_PX) * Math.SQRT1_2]);
    expect(marks.map((m) => m.conflicts)).toEqual([0, 1, 0]);
  });

  it("places each bucket at its start, a hair narrower than its span", () => {
    expect(marks.map((m) => [m.x, m.w])).toEqual([[0, 9.5], [10, 9.5], [20, 9.5]]);
  });
});

describe("bar scale", () => {
  it("keeps one change visible next to a 187-chunk upload, and still orders counts", () => {
    expect(barHeight(1, 187)).toBeGreaterThanOrEqual(MIN_BAR_PX + 2);
    expect(barHeight(0, 187)).toBe(0);
    expect(barHeight(2, 187)).toBeGreaterThan(barHeight(1, 187));
    expect(barHeight(187, 187)).toBe(BAR_MAX_PX);
  });
});

describe("hover read-out", () => {
  const tl = { from_ms: 1000, to_ms: 1300, bucket_ms: 100, buckets: [bucket(1000, 1, 0, 1), bucket(1100, 3, 2, 0), bucket(1200, 0, 1, 2)] };
  it("finds the bucket under the pointer and names its counts", () => {
    expect(bucketAt(tl, 1150)).toEqual(tl.buckets[1]);
    expect(bucketAt(tl, 999)).toBeNull();
    expect(bucketAt(tl, 1300)).toBeNull();
    expect(bucketText(tl.buckets[0])).toBe("1 chunk change · 0 conflicts · 1 robot active");
    expect(bucketText(tl.buckets[1])).toBe("3 chunk changes · 2 conflicts · 0 robots active");
  });
});

describe("timeTicks", () => {
  const at = (h: number, m = 0, s = 0, d = 24) => Date.UTC(2026, 10, d, h, m, s);
  it("labels an hour every 10 minutes on round UTC instants at 800 px", () => {
    const ticks = timeTicks(at(13, 2), at(14, 2), 800);
    expect(ticks.map((t) => t.label)).toEqual(["13:10", "13:20", "13:30", "13:40", "13:50", "14:00"]);
    expect(ticks[0].t).toBe(at(13, 10));
  });
  it("names the day across days and keeps labels apart", () => {
    const ticks = timeTicks(at(0, 0, 0, 18), at(0, 0, 0, 25), 800);
    expect(ticks[0].label).toBe("11-18 00:00");
    const gaps = ticks.slice(1).map((t, i) => ((t.t - ticks[i].t) / (7 * 86_400_000)) * 800);
    expect(Math.min(...gaps)).toBeGreaterThanOrEqual(90);
  });
  it("shows seconds under a minute's step", () => {
    expect(timeTicks(at(14, 0, 0), at(14, 0, 30), 800)[1].label).toBe("14:00:05");
  });
  it("never lets two labels overlap, over generated spans, widths and label widths", () => {
    let seed = 12345;
    const rnd = () => ((seed = (Math.imul(seed, 1103515245) + 12345) >>> 0) / 2 ** 32);
    for (let k = 0; k < 2000; k++) {
      const span = Math.round(10 ** (3 + rnd() * 6.5)); // a second to about 36 days
      const from = Date.UTC(2026, 10, 1) + Math.round(rnd() * 30 * 86_400_000);
      const width = 120 + Math.round(rnd() * 2400);
      const fontPx = 9 + rnd() * 6;
      const labelPx = (label: string) => estimateLabelPx(label, fontPx);
      // The plots' axis (50 px between grid lines at least) and the timeline strip's (90).
      for (const minGap of [50, 90]) {
        const ticks = timeTicks(from, from + span, width, minGap, labelPx);
        const x = (t: number) => ((t - from) / span) * width;
        ticks.forEach((tk, i) => {
          expect(tk.t).toBeGreaterThanOrEqual(from);
          expect(tk.t).toBeLessThanOrEqual(from + span);
          if (i === 0) return;
          const prev = ticks[i - 1];
          const room = x(tk.t) - x(prev.t) - (labelPx(tk.label) + labelPx(prev.label)) / 2;
          expect(room, `${span} ms over ${width} px: ${prev.label} | ${tk.label}`).toBeGreaterThan(0);
          expect(x(tk.t) - x(prev.t)).toBeGreaterThanOrEqual(minGap - 1e-9);
        });
      }
    }
  });
  it("labels a week of plots at 1280 px by the day, apart", () => {
    const ticks = timeTicks(at(0, 0, 0, 18), at(0, 0, 0, 25), 1200, 50);
    expect(ticks.every((t) => /^11-\d\d \d\d:00$/.test(t.label))).toBe(true);
    expect(ticks.length).toBeGreaterThanOrEqual(7);
  });
});
