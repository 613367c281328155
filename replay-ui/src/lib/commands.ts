/**
 * Operators' commands as the replay shows them: the API's shape, a command's state at an
 * instant (sent, then the robot's ack: accepted or rejected with its reason, then its
 * outcome: done, failed or cancelled), whether a robot stands paused at an instant, and the
 * timeline's marks. Pure: the requests are in lib/commandapi.ts.
 */
import type { TimelineMark } from "./annotations";

export const COMMAND_KINDS = ["pause", "resume", "goto_poi", "cancel"] as const;
export type CommandKind = (typeof COMMAND_KINDS)[number];

export interface CommandAnswer {
  ts_ms: number;
  status: string; // ack: accepted | rejected; outcome: done | failed | cancelled
  reason: string;
}

export interface Command {
  commandId: string;
  robotId: string;
  kind: string;
  poiId: string | null;
  target: { x: number; y: number; heading: number | null } | null;
  issuedBy: string;
  issued_ms: number;
  ack: CommandAnswer | null;
  outcome: CommandAnswer | null;
}

export type CommandState = "sent" | "accepted" | "rejected" | "done" | "failed" | "cancelled";

/** A command's state at `at`: the answers that came by then (null: not issued yet). */
export function commandState(c: Command, at: number): { state: CommandState; reason: string; ts_ms: number } | null {
  if (c.issued_ms > at) return null;
  if (c.outcome && c.outcome.ts_ms <= at) return { state: c.outcome.status as CommandState, reason: c.outcome.reason, ts_ms: c.outcome.ts_ms };
  if (c.ack && c.ack.ts_ms <= at) return { state: c.ack.status as CommandState, reason: c.ack.reason, ts_ms: c.ack.ts_ms };
  return { state: "sent", reason: "", ts_ms: c.issued_ms };
}

/** How the command reads in a list or a mark's title: "pause robot-1 by operator:ops: accepted"
 * (a point of interest by its name in `names` when known, else by its id). */
export function commandText(c: Command, at = Infinity, names?: ReadonlyMap<string, string>): string {
  const s = commandState(c, at);
  const what = c.kind === "goto_poi" ? `go to ${(c.poiId && names?.get(c.poiId)) ?? c.poiId ?? "?"}` : c.kind;
  const state = s ? `${s.state}${s.reason ? ` (${s.reason})` : ""}` : "not issued yet";
  return `${what} ${c.robotId} by ${c.issuedBy}: ${state}`;
}

/** Whether `robotId` stands paused at `at`: its latest pause or resume accepted by then is a pause. */
export function pausedAt(commands: readonly Command[], robotId: string, at: number): boolean {
  let latest: Command | null = null;
  for (const c of commands) {
    if (c.robotId !== robotId || (c.kind !== "pause" && c.kind !== "resume")) continue;
    const s = commandState(c, at);
    // A rejected command changed nothing; an accepted one counts from when it was issued.
    if (!s || s.state === "rejected" || s.state === "sent" || s.state === "failed") continue;
    if (!latest || c.issued_ms >= latest.issued_ms) latest = c;
  }
  return latest?.kind === "pause";
}

/** Whether the command is still waiting for an answer the page should poll for. */
export function awaiting(c: Command): boolean {
  return !c.ack || (c.ack.status === "accepted" && !c.outcome);
}

/** The timeline's marks: one per command, at its issue, titled with its answers. */
export function commandMarks(commands: readonly Command[], names?: ReadonlyMap<string, string>): TimelineMark[] {
  return commands.map((c) => ({ key: `c:${c.commandId}`, ts_ms: c.issued_ms, kind: "command", title: commandText(c, Infinity, names) }));
}

/** The commands of two lists, one per id (the later read wins), oldest first. */
export function mergeCommands(a: readonly Command[], b: readonly Command[]): Command[] {
  const byId = new Map<string, Command>();
  for (const c of [...a, ...b]) byId.set(c.commandId, c);
  return [...byId.values()].sort((x, y) => x.issued_ms - y.issued_ms);
}
