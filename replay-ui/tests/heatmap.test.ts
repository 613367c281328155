import { describe, expect, it } from "vitest";
import { formatHeatmap, formatValue, heatmapUrl, parseHeatmap, RAMP, rampColour, scaleBar } from "../src/lib/heatmap";
import { oldestReadable } from "../src/lib/retention";
import { formatUrlState, parseUrlState } from "../src/lib/urlstate";

describe("heatmap", () => {
  it("keeps its kind and cell in the address, the default cell left out", () => {
    expect(formatHeatmap({ kind: "occupancy", cell: 0.5 })).toBe("occupancy");
    expect(formatHeatmap({ kind: "dwell", cell: 2 })).toBe("dwell,2");
    for (const s of [{ kind: "speed" as const, cell: 0.5 }, { kind: "incidents" as const, cell: 1.5 }, { kind: "dwell" as const, cell: 20 }]) {
      expect(parseHeatmap(formatHeatmap(s))).toEqual(s);
      const url = formatUrlState({ ...parseUrlState("?t=5"), heatmap: s });
      expect(parseUrlState(url).heatmap).toEqual(s);
    }
    expect(parseUrlState("?t=5").heatmap).toBeNull();
    // Not a kind, or a cell the API does not keep (not a multiple of 0.5 m, over 20 m): none.
    for (const bad of ["heat", "occupancy,0.3", "occupancy,0", "occupancy,20.5", "occupancy,x", ""]) {
      expect(parseHeatmap(bad)).toBeNull();
    }
  });

  it("asks for the span, its start no older than the history keeps", () => {
    const now = Date.UTC(2026, 10, 30, 12);
    const url = new URL(heatmapUrl("", { kind: "dwell", cell: 1 }, [now - 3_600_000, now], now, "png"), "http://x");
    expect(url.pathname).toBe("/api/v1/heatmap");
    expect(Object.fromEntries(url.searchParams)).toEqual({
      kind: "dwell", cell: "1", format: "png", from: String(now - 3_600_000), to: String(now),
    });
    const week = new URL(heatmapUrl("", { kind: "occupancy", cell: 0.5 }, [now - 8 * 86_400_000, now], now), "http://x");
    expect(Number(week.searchParams.get("from"))).toBe(oldestReadable(now));
  });

  it("colours as the PNG does: the ramp's stops at its ends, between them linearly", () => {
    expect(rampColour(0)).toBe(`rgb(${RAMP[0].join(", ")})`);
    expect(rampColour(1)).toBe(`rgb(${RAMP[RAMP.length - 1].join(", ")})`);
    expect(rampColour(0.25)).toBe(`rgb(${RAMP[1].join(", ")})`);
    expect(rampColour(-1)).toBe(rampColour(0));
    expect(rampColour(2)).toBe(rampColour(1));
    expect(rampColour(0.125)).toBe("rgb(59, 86, 165)");
  });

  it("says values in the kind's unit", () => {
    expect(formatValue(42, "seconds")).toBe("42 s");
    expect(formatValue(125, "seconds")).toBe("2 min 05 s");
    expect(formatValue(7_500, "robot-seconds")).toBe("2 h 05 min (robot time)");
    expect(formatValue(0.4567, "m/s")).toBe("0.46 m/s");
    expect(formatValue(1, "incidents")).toBe("1 incident");
    expect(formatValue(3, "incidents")).toBe("3 incidents");
  });

  it("draws a scale bar of a round length no longer than its room", () => {
    for (let k = 0; k < 200; k++) {
      const metresPerPx = 10 ** (k / 40 - 3); // 1 mm to 100 m a pixel
      const bar = scaleBar(metresPerPx, 120);
      expect(bar.px).toBeLessThanOrEqual(120 + 1e-9);
      expect(bar.px).toBeGreaterThan(120 / 5 - 1e-9); // the next round length would not fit
      const mantissa = bar.metres / 10 ** Math.floor(Math.log10(bar.metres) + 1e-12);
      expect([1, 2, 5].some((m) => Math.abs(mantissa - m) < 1e-9)).toBe(true);
    }
    expect(scaleBar(0.05, 120)).toEqual({ metres: 5, px: 100, label: "5 m" });
    expect(scaleBar(0.001, 120).label).toBe("10 cm");
    expect(scaleBar(20, 120).label).toBe("2 km");
  });
});
