import { describe, expect, it } from "vitest";
import { awaiting, commandMarks, commandState, commandText, mergeCommands, pausedAt, type Command } from "../src/lib/commands";

function cmd(id: string, kind: string, issued: number, ack?: [number, string, string?], outcome?: [number, string, string?]): Command {
  return {
    commandId: id, robotId: "r1", kind, poiId: kind === "goto_poi" ? "dock" : null, target: null, issuedBy: "operator:ops", issued_ms: issued,
    ack: ack ? { ts_ms: ack[0], status: ack[1], reason: ack[2] ?? "" } : null,
    outcome: outcome ? { ts_ms: outcome[0], status: outcome[1], reason: outcome[2] ?? "" } : null,
  };
}

describe("a command's state at an instant", () => {
  const c = cmd("a", "goto_poi", 1000, [1500, "accepted"], [9000, "done"]);
  it("follows the answers as they came", () => {
    expect(commandState(c, 999)).toBeNull();
    expect(commandState(c, 1000)?.state).toBe("sent");
    expect(commandState(c, 1499)?.state).toBe("sent");
    expect(commandState(c, 1500)?.state).toBe("accepted");
    expect(commandState(c, 8999)?.state).toBe("accepted");
    expect(commandState(c, 9000)?.state).toBe("done");
  });
  it("carries a rejection's reason into its text", () => {
    const r = cmd("b", "pause", 1000, [1100, "rejected", "already paused"]);
    expect(commandState(r, 2000)).toEqual({ state: "rejected", reason: "already paused", ts_ms: 1100 });
    expect(commandText(r)).toBe("pause r1 by operator:ops: rejected (already paused)");
    expect(commandText(c, 1200)).toBe("go to dock r1 by operator:ops: sent");
    expect(commandText(c, 1600, new Map([["dock", "dock 7"]]))).toBe("go to dock 7 r1 by operator:ops: accepted");
  });
  it("awaits an ack, then an accepted command's outcome", () => {
    expect(awaiting(cmd("x", "pause", 1))).toBe(true);
    expect(awaiting(cmd("x", "pause", 1, [2, "accepted"]))).toBe(true);
    expect(awaiting(cmd("x", "pause", 1, [2, "rejected", "no"]))).toBe(false);
    expect(awaiting(cmd("x", "pause", 1, [2, "accepted"], [3, "done"]))).toBe(false);
  });
});

describe("paused at an instant", () => {
  const cs = [cmd("p", "pause", 1000, [1200, "accepted"], [1300, "done"]), cmd("r", "resume", 5000, [5100, "accepted"])];
  it("is paused from the accepted pause until the accepted resume", () => {
    expect(pausedAt(cs, "r1", 900)).toBe(false);
    expect(pausedAt(cs, "r1", 1100)).toBe(false); // sent, not yet accepted
    expect(pausedAt(cs, "r1", 1200)).toBe(true);
    expect(pausedAt(cs, "r1", 5050)).toBe(true); // the resume is not accepted yet
    expect(pausedAt(cs, "r1", 5100)).toBe(false);
    expect(pausedAt(cs, "r2", 2000)).toBe(false);
  });
  it("ignores rejected pauses and resumes and other kinds", () => {
    const more = [...cs, cmd("r2", "resume", 2000, [2100, "rejected", "busy"]), cmd("g", "goto_poi", 3000, [3100, "accepted"])];
    expect(pausedAt(more, "r1", 4000)).toBe(true);
    expect(pausedAt([cmd("p2", "pause", 1, [2, "rejected", "e-stop"])], "r1", 10)).toBe(false);
  });
});

describe("the timeline's marks", () => {
  it("marks each command once at its issue, the latest read winning", () => {
    const old = cmd("a", "pause", 1000);
    const answered = cmd("a", "pause", 1000, [1100, "accepted"]);
    const merged = mergeCommands([old, cmd("b", "resume", 500)], [answered]);
    expect(merged.map((c) => c.commandId)).toEqual(["b", "a"]);
    const marks = commandMarks(merged);
    expect(marks.map((m) => [m.kind, m.ts_ms])).toEqual([["command", 500], ["command", 1000]]);
    expect(marks[1].title).toBe("pause r1 by operator:ops: accepted");
  });
});
