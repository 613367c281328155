import { describe, expect, it } from "vitest";
import { formatUrlState, parseUrlState, toInputValue } from "../src/lib/urlstate";
import {
  fitSpan, followPlayhead, holds, MIN_SPAN_MS, openingSpan, playheadAfterViewMove, presetSpan, typedSpan, wheelSpan, widerSpan,
  type Bounds, type Span,
} from "../src/lib/viewspan";

const HOUR = 3_600_000;
const DAY = 24 * HOUR;
const PRESETS = [HOUR, 6 * HOUR, DAY, 7 * DAY];

function random(seed: number) {
  return () => {
    seed = (seed * 1103515245 + 12345) % 2147483648;
    return seed / 2147483648;
  };
}

/** The page as far as the timeline is concerned: what TimelineStrip.vue and the engine do with these rules. */
interface Page {
  bounds: Bounds;
  view: Span;
  playhead: number;
  live: boolean;
  history: Span[];
}

/** A move of the view (the strip's show()): a playhead it leaves out is sought into it, which leaves live. */
function showView(p: Page, span: Span) {
  p.view = span;
  const t = playheadAfterViewMove(span, p.playhead);
  if (t !== null) {
    p.playhead = t;
    p.live = false;
  }
}

/** A move of the playhead (a seek, playing, live): the engine clamps it, the view follows. */
function movePlayhead(p: Page, t: number) {
  p.playhead = Math.round(Math.min(p.bounds.now, Math.max(p.bounds.minMs, t)));
  p.view = followPlayhead(p.view, p.playhead, p.bounds);
}

function checkInvariants(p: Page, what: string) {
  const [a, b] = p.view;
  const ctx = `${what}: view ${a}..${b}, playhead ${p.playhead}, live ${p.live}`;
  expect(holds(p.view, p.playhead), ctx).toBe(true);
  expect(b - a, ctx).toBeGreaterThanOrEqual(MIN_SPAN_MS);
  expect(Number.isInteger(a) && Number.isInteger(b), ctx).toBe(true);
  if (p.live) expect(p.playhead, ctx).toBe(p.bounds.now);
}

describe("the timeline's view and the playhead", () => {
  it("keeps the playhead in view after any sequence of zooms, presets, typed spans, seeks, playing and live", () => {
    for (let run = 0; run < 300; run++) {
      const rnd = random(run + 1);
      const now0 = Date.UTC(2026, 10, 29, 12) + Math.floor(rnd() * DAY);
      const bounds = { minMs: now0 - 7 * DAY + 60_000, now: now0 };
      const startLive = rnd() < 0.5;
      const t0 = startLive ? now0 : Math.round(bounds.minMs + rnd() * (now0 - bounds.minMs));
      const p: Page = { bounds, live: startLive, playhead: t0, history: [],
        view: openingSpan({ live: startLive, t: t0, span: null }, bounds) };
      checkInvariants(p, "opened");
      for (let step = 0; step < 40; step++) {
        const [a, b] = p.view;
        const at = (f: number) => a + f * (b - a);
        const op = Math.floor(rnd() * 9);
        let what: string;
        if (op === 0) {
          // A drag over part of the strip (at least a second).
          const x0 = rnd();
          const x1 = rnd();
          what = `drag ${x0.toFixed(3)}..${x1.toFixed(3)}`;
          if (Math.abs(at(x1) - at(x0)) >= 1000) {
            p.history.push(p.view);
            showView(p, fitSpan(at(Math.min(x0, x1)), at(Math.max(x0, x1)), bounds));
          }
        } else if (op === 1) {
          const f = rnd() < 0.5 ? 0.8 : 1.25;
          what = `wheel ${f}`;
          showView(p, wheelSpan(p.view, at(rnd()), f, bounds));
        } else if (op === 2) {
          const len = PRESETS[Math.floor(rnd() * PRESETS.length)];
          what = `preset ${len}`;
          p.history.push(p.view);
          const span = presetSpan(len, p.playhead, p.live, bounds);
          // A preset holds the playhead: it never moves it.
          expect(holds(span, p.playhead), what).toBe(true);
          showView(p, span);
        } else if (op === 3) {
          what = "zoom out";
          p.history.push(p.view);
          showView(p, widerSpan(p.view, bounds));
        } else if (op === 4) {
          what = "back";
          const prev = p.history.pop();
          if (prev) showView(p, fitSpan(prev[0], prev[1], bounds));
        } else if (op === 5) {
          const from = bounds.minMs - DAY + rnd() * 9 * DAY;
          const to = from + (rnd() - 0.2) * 3 * DAY;
          what = `typed ${toInputValue(from)} → ${toInputValue(to)}`;
          const r = typedSpan(toInputValue(from), toInputValue(to), bounds);
          if ("span" in r) {
            p.history.push(p.view);
            showView(p, fitSpan(r.span[0], r.span[1], bounds));
          }
        } else if (op === 6) {
          const t = bounds.minMs + rnd() * (bounds.now - bounds.minMs);
          what = `seek ${t}`;
          p.live = false;
          movePlayhead(p, t);
        } else if (op === 7) {
          // Time passes: live follows now, playing moves the playhead at some speed.
          const dt = Math.floor(rnd() * 10_000);
          bounds.now += dt;
          bounds.minMs += dt;
          what = `time +${dt}`;
          if (p.live) movePlayhead(p, bounds.now);
          else movePlayhead(p, p.playhead + (rnd() < 0.5 ? 1 : -1) * dt * [1, 60, 3600][Math.floor(rnd() * 3)]);
          if (!p.live && p.playhead >= bounds.now && rnd() < 0.5) p.live = true;
        } else {
          what = "live";
          p.live = true;
          movePlayhead(p, bounds.now);
        }
        checkInvariants(p, `run ${run} step ${step} ${what}`);
      }
    }
  });

  it("a drag into the past while live leaves live at the dragged span's end; one reaching now stays live", () => {
    const now = Date.UTC(2026, 10, 29, 12);
    const bounds = { minMs: now - 7 * DAY, now };
    for (let k = 1; k < 50; k++) {
      const end = now - k * 60_000;
      const span = fitSpan(end - HOUR, end, bounds);
      expect(playheadAfterViewMove(span, now)).toBe(end);
    }
    expect(playheadAfterViewMove(fitSpan(now - 10 * 60_000, now, bounds), now)).toBeNull();
  });

  it("centres presets on a paused playhead (within the history kept and now), and ends them now when live", () => {
    const rnd = random(7);
    for (let i = 0; i < 2000; i++) {
      const now = Date.UTC(2026, 10, 29) + Math.floor(rnd() * DAY);
      const bounds = { minMs: now - 7 * DAY + 60_000, now };
      const len = PRESETS[i % PRESETS.length];
      const t = Math.round(bounds.minMs + rnd() * (now - bounds.minMs));
      const span = presetSpan(len, t, false, bounds);
      expect(holds(span, t)).toBe(true);
      expect(span[0]).toBeGreaterThanOrEqual(bounds.minMs);
      expect(span[1]).toBeLessThanOrEqual(now);
      expect(span[1] - span[0]).toBe(Math.min(len, Math.floor(now - bounds.minMs)));
      // Centred wherever the ends allow it.
      if (t - len / 2 >= bounds.minMs && t + len / 2 <= now) expect(span).toEqual([t - len / 2, t + len / 2]);
      expect(presetSpan(len, now, true, bounds)).toEqual([now - Math.min(len, Math.floor(now - bounds.minMs)), now]);
    }
  });

  it("reopens from its address the span and the instant that were seen", () => {
    const rnd = random(11);
    for (let i = 0; i < 1000; i++) {
      const now = Date.UTC(2026, 10, 29) + Math.floor(rnd() * DAY);
      const bounds = { minMs: now - 7 * DAY + 60_000, now };
      const live = rnd() < 0.3;
      const t = live ? now : Math.round(bounds.minMs + 1000 + rnd() * (now - bounds.minMs - 1000));
      const len = Math.max(MIN_SPAN_MS, Math.round(rnd() * rnd() * 7 * DAY));
      const view = live ? fitSpan(now - len, now, bounds) : followPlayhead(fitSpan(t - rnd() * len, t + len, bounds), t, bounds);
      expect(holds(view, t)).toBe(true);
      const state = { live, t, speed: 60 as const, dir: 1 as const, playing: false, view: null, follow: null, layers: null,
        selected: null, panels: ["changes"], area: null, changeRobot: null, span: view, plot: [], incidentKinds: [], incidentRobot: null, incident: null, heatmap: null };
      const reopened = parseUrlState(formatUrlState(state));
      expect(reopened).toEqual({ ...state, t: live ? null : t, speed: live ? 1 : 60, tProblem: null });
      expect(openingSpan(reopened, bounds)).toEqual(view);
      // A live link opened later: the same length, ending at the later now.
      const later = { minMs: bounds.minMs + 5 * HOUR, now: now + 5 * HOUR };
      if (live) expect(openingSpan(reopened, later)).toEqual(fitSpan(later.now - (view[1] - view[0]), later.now, later));
    }
  });

  it("opens on an hour around the address's instant, or the last hour when live", () => {
    const now = Date.UTC(2026, 10, 29, 12);
    const bounds = { minMs: now - 7 * DAY, now };
    expect(openingSpan({ live: true, t: null, span: null }, bounds)).toEqual([now - HOUR, now]);
    expect(openingSpan({ live: false, t: now - DAY, span: null }, bounds)).toEqual([now - DAY - HOUR / 2, now - DAY + HOUR / 2]);
    // A hand-made address whose instant is outside its span: the span moves to it, as a seek would.
    const span = openingSpan({ live: false, t: now - 2 * DAY, span: [now - HOUR, now] }, bounds);
    expect(holds(span, now - 2 * DAY)).toBe(true);
    expect(span[1] - span[0]).toBe(HOUR);
  });
});

describe("a typed span", () => {
  const now = Date.UTC(2026, 10, 29, 12);
  const bounds = { minMs: now - 7 * DAY + 60_000, now };

  it("is the span typed, to the second, wherever it lies within the history kept", () => {
    const rnd = random(3);
    for (let i = 0; i < 1000; i++) {
      const a = Math.floor((bounds.minMs + rnd() * (now - bounds.minMs)) / 1000) * 1000 + 1000;
      const b = Math.min(Math.floor(now / 1000) * 1000, a + 1000 + Math.floor(rnd() * 3 * DAY / 1000) * 1000);
      if (b - a < 1000) continue;
      const r = typedSpan(toInputValue(a), toInputValue(b), bounds);
      expect(r).toEqual({ span: [a, b], note: null });
    }
  });

  it("is cut to the history kept and to now, and says so", () => {
    const r = typedSpan(toInputValue(now - 9 * DAY), toInputValue(now + DAY), bounds);
    expect(r).toEqual({ span: [bounds.minMs, now], note: "the span starts at the oldest instant kept and ends now" });
  });

  it("says what is wrong with what cannot be a span", () => {
    const cases: [string, string, RegExp][] = [
      ["yesterday", "2026-11-29 10:00", /start "yesterday" is not a time: write a UTC time as/],
      ["2026-11-29 10:00", "", /end "" is not a time/],
      ["2026-11-29 10:00", "2026-11-29 09:00", /end must be after its start/],
      ["2026-11-29 10:00:00", "2026-11-29 10:00:00.500", /at least a second/],
      ["2026-11-01 10:00", "2026-11-02 10:00", /older than the history keeps/],
      ["2026-11-30 10:00", "2026-11-30 11:00", /in the future/],
    ];
    for (const [a, b, want] of cases) {
      const r = typedSpan(a, b, bounds);
      expect("error" in r && r.error, `${a} → ${b}`).toMatch(want);
    }
  });
});
