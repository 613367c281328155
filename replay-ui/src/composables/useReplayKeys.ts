/**
 * The replay's keys, on the window for as long as the page is mounted: space play/pause,
 * ←/→ step, Shift+←/→ previous/next change, [ / ] previous/next incident, ↑/↓ speed, L live,
 * Esc unselect. Not while
 * typing in a field; a checkbox keeps no keys of its own (space after a click on a layer
 * is play/pause, not the checkbox again).
 */
import { onBeforeUnmount, onMounted } from "vue";

export interface ReplayKeyActions {
  togglePlay(): void;
  step(sign: 1 | -1): void;
  stepChange(sign: 1 | -1): void;
  stepIncident(sign: 1 | -1): void;
  speedBy(delta: 1 | -1): void;
  goLive(): void;
  unselect(): void;
}

export function keyAction(e: Pick<KeyboardEvent, "key" | "shiftKey">, a: ReplayKeyActions): (() => void) | null {
  const arrow = e.key === "ArrowRight" ? 1 : e.key === "ArrowLeft" ? -1 : 0;
  if (arrow && e.shiftKey) return () => a.stepChange(arrow);
  if (arrow) return () => a.step(arrow);
  // The characters, not the keys: wherever a layout puts them (no browser or map shortcut uses them).
  if (e.key === "[") return () => a.stepIncident(-1);
  if (e.key === "]") return () => a.stepIncident(1);
  if (e.key === " ") return a.togglePlay;
  if (e.key === "ArrowUp") return () => a.speedBy(1);
  if (e.key === "ArrowDown") return () => a.speedBy(-1);
  if (e.key === "l" || e.key === "L") return a.goLive;
  if (e.key === "Escape") return a.unselect;
  return null;
}

export function useReplayKeys(actions: ReplayKeyActions): void {
  function onKey(e: KeyboardEvent) {
    const target = e.target as HTMLInputElement | null;
    const tag = target?.tagName;
    const typing = (tag === "INPUT" && target?.type !== "checkbox") || tag === "SELECT" || tag === "TEXTAREA";
    if (typing) return;
    const act = keyAction(e, actions);
    if (!act) return;
    if (e.key !== "l" && e.key !== "L" && e.key !== "Escape") e.preventDefault();
    act();
  }
  onMounted(() => window.addEventListener("keydown", onKey));
  onBeforeUnmount(() => window.removeEventListener("keydown", onKey));
}
