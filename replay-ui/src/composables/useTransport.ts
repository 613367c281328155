/**
 * The transport: play, pause, step, speed, live, seek, and the time box that jumps to an
 * instant typed in it. Each acts on the engine's clock at the wall-clock instant of the
 * click or key.
 */
import { ref, type Ref } from "vue";
import { SPEEDS, type Speed } from "../lib/clock";
import type { ReplayEngine } from "../lib/engine";
import { RETENTION_MS } from "../lib/retention";
import { clampToRetention, fromInputValue, PICKER_FORMATS, toInputValue, type UrlState } from "../lib/urlstate";

function wall() {
  return Date.now();
}

/** `notice`: where to tell the user about a time that could not be used as given. */
export function useTransport(engine: ReplayEngine, notice: Ref<string | null>) {
  const pickerValue = ref("");
  const pickerInvalid = ref(false);

  function seek(t: number) {
    void engine.seek(t);
  }

  function togglePlay() {
    engine.clock.toggle(wall());
    if (!engine.clock.live) engine.live.stop();
  }

  function play(dir: 1 | -1) {
    engine.live.stop();
    engine.clock.setDirection(dir, wall());
    engine.clock.play(wall());
  }

  function step(sign: 1 | -1) {
    engine.live.stop();
    engine.clock.step(sign, wall());
    void engine.seek(engine.clock.time(wall()));
  }

  function setSpeed(s: Speed) {
    engine.setSpeed(s);
  }

  function speedBy(delta: 1 | -1) {
    const i = SPEEDS.indexOf(engine.clock.speed) + delta;
    if (i >= 0 && i < SPEEDS.length) setSpeed(SPEEDS[i]);
  }

  function goLive() {
    void engine.goLive();
  }

  /** Leaves live mode, pauses and seeks: a pick in a list shows that instant and stays there. */
  function pauseAt(t: number) {
    engine.live.stop();
    engine.clock.pause(wall());
    seek(t);
  }

  /** The time box's instant, within the history kept. */
  function pick() {
    const t = fromInputValue(pickerValue.value);
    pickerInvalid.value = t === null;
    if (t === null) {
      notice.value = `"${pickerValue.value.trim()}" is not a time the box can read: write ${PICKER_FORMATS}`;
      return;
    }
    const clamped = clampToRetention(t, wall(), RETENTION_MS);
    notice.value = clamped.problem?.replace("the link's time", "that time") ?? null;
    seek(clamped.t);
  }

  /** The time box follows the playhead, except while the user types in it. */
  function showPlayhead() {
    if (document.activeElement?.id !== "picker") pickerValue.value = toInputValue(engine.playhead);
  }

  /** Where the address says to start: live, or its instant (within the history kept) at its speed and direction. */
  async function start(initial: UrlState) {
    engine.clock.setSpeed(initial.speed, wall());
    engine.clock.setDirection(initial.dir, wall());
    if (initial.live || initial.t === null) await engine.goLive();
    else {
      const clamped = clampToRetention(initial.t, wall(), RETENTION_MS);
      notice.value = clamped.problem;
      await engine.seek(clamped.t);
      if (initial.playing) engine.clock.play(wall());
    }
  }

  return { pickerValue, pickerInvalid, seek, togglePlay, play, step, setSpeed, speedBy, goLive, pauseAt, pick, showPlayhead, start };
}
