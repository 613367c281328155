/**
 * VDA 5050 vehicles' facts beyond their poses (GET /api/v1/robots/vda5050 and
 * /api/v1/robots/{id}/vda5050): errors and warnings, exact connection states, factsheets.
 * A vehicle repeats its active errors in every state; a state without errors after one
 * with some clears them (errorClears), so the errors at T are those of the latest error
 * instant at or before T, unless a clear came between.
 */
import { getJson } from "./api";

export interface VdaError { ts_ms: number; level: string; type: string; description: string }
export interface VdaConnection { ts_ms: number; state: string; sent_ms: number }
/** The parts of a VDA 5050 factsheet the page reads: a vehicle's document, so any of them
 * may be missing or of another type. */
export interface Factsheet {
  manufacturer?: unknown;
  serialNumber?: unknown;
  typeSpecification?: { seriesName?: unknown };
  physicalParameters?: { speedMax?: unknown };
  [field: string]: unknown;
}

export interface VdaVehicle {
  robotId: string;
  manufacturer: string;
  serialNumber: string;
  online: boolean | null;
  errors: VdaError[];
  connections: VdaConnection[];
  factsheet: { ts_ms: number; vda_version: string; factsheet: Factsheet } | null;
  errorClears: number[];
}

/** One error or warning where it began (a timeline mark). */
export interface ErrorMark { ts_ms: number; robotId: string; level: string; type: string; description: string }

export interface FactsheetSummary { manufacturer: string; serialNumber: string; series: string | null; speedMax: number | null; version: string }

export function fleetFacts(base: string, from: number, to: number): Promise<VdaVehicle[]> {
  return getJson<VdaVehicle[]>(`${base}/api/v1/robots/vda5050?from=${Math.floor(from)}&to=${Math.floor(to)}`, "the robots' VDA 5050 states");
}

export function vehicleFacts(base: string, robotId: string, from: number, to: number): Promise<VdaVehicle> {
  return getJson<VdaVehicle>(`${base}/api/v1/robots/${encodeURIComponent(robotId)}/vda5050?from=${Math.floor(from)}&to=${Math.floor(to)}`, `${robotId}'s VDA 5050 state`);
}

/** A robot id that names a VDA 5050 vehicle (`<manufacturer>:<serialNumber>`, escaped). */
export function isVehicleId(robotId: string): boolean {
  return /^[^:]+:[^:]+$/.test(robotId);
}

const errorKey = (e: VdaError) => `${e.level}\u0000${e.type}\u0000${e.description}`;

/** Each error's onsets: where it is in a state and was not in the vehicle's state before. */
export function errorMarks(vehicles: VdaVehicle[]): ErrorMark[] {
  const marks: ErrorMark[] = [];
  for (const v of vehicles) {
    const instants = new Map<number, VdaError[]>();
    for (const c of v.errorClears) instants.set(c, []);
    for (const e of v.errors) instants.set(e.ts_ms, [...(instants.get(e.ts_ms) ?? []), e]);
    let active = new Set<string>();
    for (const t of [...instants.keys()].sort((a, b) => a - b)) {
      const errs = instants.get(t)!;
      for (const e of errs) if (!active.has(errorKey(e))) marks.push({ ...e, robotId: v.robotId });
      active = new Set(errs.map(errorKey));
    }
  }
  // Warnings first at one instant: a fatal error's mark is drawn over them.
  const rank = (m: ErrorMark) => (m.level === "WARNING" ? 0 : 1);
  return marks.sort((a, b) => a.ts_ms - b.ts_ms || rank(a) - rank(b) || a.robotId.localeCompare(b.robotId));
}

/** The vehicle's errors and warnings active at `t` (fatal ones first). */
export function errorsAt(v: VdaVehicle | undefined, t: number): VdaError[] {
  if (!v) return [];
  let last = -Infinity;
  for (const e of v.errors) if (e.ts_ms <= t && e.ts_ms > last) last = e.ts_ms;
  if (last === -Infinity || v.errorClears.some((c) => c > last && c <= t)) return [];
  const rank = (e: VdaError) => (e.level === "WARNING" ? 1 : 0);
  return v.errors.filter((e) => e.ts_ms === last).sort((a, b) => rank(a) - rank(b) || a.type.localeCompare(b.type));
}

/** The latest connection state at or before `t` (null: none in the facts read). */
export function connectionAt(v: VdaVehicle | undefined, t: number): VdaConnection | null {
  let at: VdaConnection | null = null;
  for (const c of v?.connections ?? []) if (c.ts_ms <= t && (!at || c.ts_ms >= at.ts_ms)) at = c;
  return at;
}

export function factsheetSummary(v: VdaVehicle | null): FactsheetSummary | null {
  const sheet = v?.factsheet;
  if (!v || !sheet) return null;
  const f = sheet.factsheet;
  const speed = f.physicalParameters?.speedMax;
  return {
    manufacturer: typeof f.manufacturer === "string" ? f.manufacturer : v.manufacturer,
    serialNumber: typeof f.serialNumber === "string" ? f.serialNumber : v.serialNumber,
    series: typeof f.typeSpecification?.seriesName === "string" ? f.typeSpecification.seriesName : null,
    speedMax: typeof speed === "number" ? speed : null,
    version: sheet.vda_version,
  };
}

export function errorText(e: { level: string; type: string; description: string }): string {
  return `${e.level} ${e.type}${e.description ? `: ${e.description}` : ""}`;
}
