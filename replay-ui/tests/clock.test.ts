import { describe, expect, it } from "vitest";
import { PlaybackClock, SPEEDS, stepMs } from "../src/lib/clock";

const NOW = 1_000_000_000;

describe("PlaybackClock", () => {
  it("stands still while paused", () => {
    const c = new PlaybackClock(NOW - 60_000, NOW);
    expect(c.time(NOW + 5_000)).toBe(NOW - 60_000);
  });

  it("runs at every speed, forwards", () => {
    for (const s of SPEEDS) {
      const start = NOW - 7 * 86_400_000;
      const c = new PlaybackClock(start, NOW);
      c.setSpeed(s, NOW);
      c.play(NOW);
      expect(c.time(NOW + 100)).toBe(start + 100 * s);
    }
  });

  it("runs backwards", () => {
    const c = new PlaybackClock(NOW - 100_000, NOW);
    c.setSpeed(60, NOW);
    c.setDirection(-1, NOW);
    c.play(NOW);
    expect(c.time(NOW + 1000)).toBe(NOW - 100_000 - 60_000);
  });

  it("does not jump when the speed changes while playing", () => {
    const c = new PlaybackClock(NOW - 100_000, NOW);
    c.play(NOW);
    c.setSpeed(8, NOW + 1000);
    expect(c.time(NOW + 1000)).toBe(NOW - 99_000);
    expect(c.time(NOW + 2000)).toBe(NOW - 99_000 + 8_000);
  });

  it("never passes now or the retention start", () => {
    const c = new PlaybackClock(NOW - 1000, NOW);
    c.minMs = NOW - 10_000;
    c.setSpeed(3600, NOW);
    c.play(NOW);
    expect(c.time(NOW + 10)).toBe(NOW + 10);
    c.setDirection(-1, NOW + 10);
    expect(c.time(NOW + 1000)).toBe(NOW - 10_000);
  });

  it("seeks, pauses where it is, and steps by the speed's step", () => {
    const c = new PlaybackClock(NOW - 1000, NOW);
    c.seek(NOW - 50_000, NOW);
    expect(c.time(NOW)).toBe(NOW - 50_000);
    c.play(NOW);
    c.pause(NOW + 500);
    expect(c.time(NOW + 9_000)).toBe(NOW - 49_500);
    c.setSpeed(8, NOW + 9_000);
    c.step(-1, NOW + 9_000);
    expect(c.time(NOW + 9_000)).toBe(NOW - 49_500 - stepMs(8));
    expect(c.playing).toBe(false);
  });

  it("follows the wall clock in live mode and leaves it on seek", () => {
    const c = new PlaybackClock(NOW - 100_000, NOW);
    c.goLive(NOW);
    expect(c.time(NOW + 1234)).toBe(NOW + 1234);
    c.seek(NOW - 5000, NOW + 2000);
    expect(c.live).toBe(false);
    expect(c.time(NOW + 3000)).toBe(NOW - 5000);
  });

  it("tells of every change asked for, not of the holds the frames make", () => {
    const actions: [string, (c: PlaybackClock) => void][] = [
      ["play", (c) => c.play(NOW)], ["pause", (c) => c.pause(NOW)], ["toggle", (c) => c.toggle(NOW)],
      ["speed", (c) => c.setSpeed(60, NOW)], ["direction", (c) => c.setDirection(-1, NOW)],
      ["seek", (c) => c.seek(NOW - 5000, NOW)], ["step", (c) => c.step(1, NOW)], ["live", (c) => c.goLive(NOW)],
    ];
    for (const [name, act] of actions) {
      for (const playing of [false, true]) {
        const c = new PlaybackClock(NOW - 60_000, NOW);
        if (playing) c.play(NOW);
        let told = 0;
        c.onChange = () => told++;
        act(c);
        expect(told, `${name}, playing: ${playing}`).toBeGreaterThan(0);
      }
    }
    const c = new PlaybackClock(NOW - 60_000, NOW);
    c.play(NOW);
    let told = 0;
    c.onChange = () => told++;
    c.hold(NOW - 30_000, NOW + 10);
    c.time(NOW + 20);
    expect(told).toBe(0);
  });
});
