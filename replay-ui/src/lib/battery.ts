/**
 * Battery levels in percent. What a level means is the robot's, not the sample's: VDA 5050
 * sends `batteryCharge` in percent (0..100); the 2019 contract's `battery_level` names no
 * scale, and its robots (the simulator among them) send percent, some a fraction (0..1).
 * A robot that ever reported more than 1 reports percent: its 5.0 is 5 %, its 0.8 is
 * 0.8 %. A robot whose every level so far lies within 0..1 reports a fraction: its 0.8 is
 * 80 %. A guess per sample cannot tell a percent robot at 0.8 % from a fraction robot at
 * 80 %, and a guess per range of values (0..5 as fifths) jumps at its boundaries.
 *
 * The page takes note of every level it reads for a robot (its robots at the playhead,
 * the live poses, the plots' per-bucket highest); where these all lie within 0..1 it asks
 * the API once for the robot's highest level over the whole retention.
 */

export type BatteryScale = "percent" | "fraction";

/** The scale of a robot whose highest reported level is `highest` (null: none known). */
export function scaleOfHighest(highest: number | null): BatteryScale {
  return highest !== null && highest > 1 ? "percent" : "fraction";
}

/** A level on `scale` in whole percent, within 0..100 (the 2019 contract bounds neither
 * end); null where the robot reported none. */
export function levelPercent(level: number | null | undefined, scale: BatteryScale): number | null {
  if (level === null || level === undefined || !Number.isFinite(level)) return null;
  const pct = scale === "fraction" ? level * 100 : level;
  return Math.round(Math.min(100, Math.max(0, pct)));
}

/** Reads a robot's highest battery level over everything stored (null: it never sent one). */
export type HighestLevelRead = (robotId: string) => Promise<number | null>;

/** What the page knows of each robot's battery scale: the highest level it saw per robot. */
export class BatteryScales {
  private highest = new Map<string, number>();
  private asked = new Set<string>();
  /** Changes whenever a robot's scale may have changed (for whoever caches percentages). */
  version = 0;

  constructor(private readHighest: HighestLevelRead | null = null) {}

  /** Where the highest level stored is read from (the page sets it once its API is known). */
  useReader(read: HighestLevelRead): void {
    this.readHighest = read;
  }

  /** Takes note of levels robot `id` reported (nulls and non-numbers are skipped). */
  note(id: string, ...levels: (number | null | undefined)[]): void {
    for (const level of levels) {
      if (level === null || level === undefined || !Number.isFinite(level)) continue;
      const before = this.highest.get(id);
      if (before === undefined || level > before) {
        if (before === undefined || scaleOfHighest(before) !== scaleOfHighest(level)) this.version++;
        this.highest.set(id, level);
      }
    }
  }

  /** The scale robot `id` reports on, from what was noted; while every level noted lies
   * within 0..1, asks the API (once per robot) for its highest level stored. */
  scale(id: string): BatteryScale {
    const scale = scaleOfHighest(this.highest.get(id) ?? null);
    if (scale === "fraction" && this.highest.has(id) && !this.asked.has(id) && this.readHighest) {
      this.asked.add(id);
      // A failed read is not asked again every frame: the levels noted meanwhile still count.
      this.readHighest(id).then((h) => this.note(id, h), () => undefined);
    }
    return scale;
  }

  /** Robot `id`'s scale once `levels` are noted (the levels about to be shown count too). */
  noted(id: string, ...levels: (number | null | undefined)[]): BatteryScale {
    this.note(id, ...levels);
    return this.scale(id);
  }

  /** Robot `id`'s `level` in percent, on its scale (the level itself noted first). */
  percent(id: string, level: number | null | undefined): number | null {
    return levelPercent(level, this.noted(id, level));
  }
}

/** The page's robots' scales (one fleet per page). */
export const batteryScales = new BatteryScales();

/** A percentage as the panels write it ("?" where the robot reported no level). */
export function batteryText(pct: number | null): string {
  return pct === null ? "?" : `${pct} %`;
}
