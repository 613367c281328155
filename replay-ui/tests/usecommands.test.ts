import { afterEach, describe, expect, it, vi } from "vitest";
import { nextTick, ref } from "vue";
import { useCommands } from "../src/composables/useCommands";
import type { Command } from "../src/lib/commands";
import { REFRESH_MS } from "../src/lib/cadence";

function cmd(id: string, kind: string, issued: number): Command {
  return { commandId: id, robotId: "r1", kind, poiId: null, target: null, issuedBy: "operator:ops", issued_ms: issued, ack: null, outcome: null };
}

/** fetch as the API answers: a list read waits for `release`, a send answers at once. */
function api(listed: Command[], made: Command) {
  let release = () => {};
  const held = new Promise<void>((r) => (release = r));
  vi.stubGlobal("fetch", async (url: string, init?: RequestInit) => {
    if (init?.method === "POST") return new Response(JSON.stringify(made), { status: 201 });
    await held;
    return new Response(JSON.stringify({ commands: listed }), { status: 200 });
  });
  return { release };
}

async function settle() {
  for (let i = 0; i < 5; i++) await new Promise((r) => setTimeout(r, 0));
  await nextTick();
}

afterEach(() => vi.unstubAllGlobals());

describe("the selected robot's commands", () => {
  it("keep a command sent while an older read was under way", async () => {
    const now = Date.now();
    const pause = cmd("p", "pause", now - 5_000);
    const goto = cmd("g", "resume", now);
    const { release } = api([pause], goto);
    const selected = ref<string | null>("r1");
    const c = useCommands({ base: "", selected, operator: () => true, span: () => [now - 60_000, now + 60_000] });
    c.tick(now); // the read begins, and is answered only after the send
    await c.send("resume");
    expect(c.recent.map((x) => x.commandId)).toEqual(["g"]);
    release();
    await settle();
    // The read's list predates the send; the sent command stays listed beside it.
    expect(c.recent.map((x) => x.commandId)).toEqual(["g", "p"]);
  });

  it("keep a sent command until a read lists it, also when the read began after the send", async () => {
    const now = Date.now();
    const pause = cmd("p", "pause", now - 5_000);
    const goto = cmd("g", "resume", now);
    const listed = [pause]; // the history has not stored the send yet
    api(listed, goto).release();
    const selected = ref<string | null>("r1");
    const c = useCommands({ base: "", selected, operator: () => true, span: () => [now - 60_000, now + 60_000] });
    await c.send("resume");
    c.tick(now); // a read begun after the send, answered without it
    await settle();
    expect(c.recent.map((x) => x.commandId)).toEqual(["g", "p"]);
    listed.push({ ...goto, ack: { status: "accepted", reason: "", ts_ms: now + 100 } });
    c.tick(now + 86_400_000); // a day on: read again; stored now, with its ack, and shown so
    await settle();
    expect(c.recent.map((x) => x.commandId)).toEqual(["g", "p"]);
    expect(c.recent[0].ack).not.toBeNull();
  });

    it("drop a send answered after another robot was selected", async () => {
    const now = Date.now();
    api([], cmd("g", "resume", now)).release();
    const selected = ref<string | null>("r1");
    const c = useCommands({ base: "", selected, operator: () => true, span: () => [now - 60_000, now + 60_000] });
    const sending = c.send("resume");
    selected.value = "r2";
    await sending;
    await settle();
    expect(c.recent).toEqual([]);
  });
});

describe("the span's commands", () => {
  /** fetch that counts the span reads (no robot selected: only those) and answers `listed`. */
  function counting(listed: Command[] = []) {
    const reads: string[] = [];
    vi.stubGlobal("fetch", async (url: string) => {
      reads.push(url);
      return new Response(JSON.stringify({ commands: listed }), { status: 200 });
    });
    return reads;
  }

  it("are read once a refresh while a live span slides with the clock, not at every tick", async () => {
    const reads = counting();
    let now = Date.now();
    vi.spyOn(Date, "now").mockImplementation(() => now);
    const live = () => [now - 3_600_000, now] as [number, number];
    const c = useCommands({ base: "", selected: ref(null), operator: () => false, span: live });
    for (let i = 0; i < 100; i++) { // 20 s of ticks five times a second
      c.tick(now);
      await settle();
      now += 200;
    }
    // One read, then one per refresh: 1 + 20 s / REFRESH_MS, not 100.
    const refreshes = Math.floor(20_000 / REFRESH_MS);
    expect(reads.length).toBeGreaterThanOrEqual(1 + refreshes - 1);
    expect(reads.length).toBeLessThanOrEqual(1 + refreshes);
    vi.restoreAllMocks();
  });

  it("are read once for a span in the past, however long the page rests on it", async () => {
    const reads = counting();
    let now = Date.now();
    vi.spyOn(Date, "now").mockImplementation(() => now);
    const span: [number, number] = [now - 86_400_000, now - 3_600_000]; // paused yesterday
    const c = useCommands({ base: "", selected: ref(null), operator: () => false, span: () => span });
    for (let i = 0; i < 50; i++) { // ten minutes, a tick every 12 s
      c.tick(span[0]);
      await settle();
      now += 12_000;
    }
    expect(reads.length).toBe(1);
    vi.restoreAllMocks();
  });

  it("are read again for a span the last read does not hold, and not for one inside it", async () => {
    const reads = counting();
    const now = Date.now();
    let span: [number, number] = [now - 86_400_000, now - 3_600_000]; // paused in the past
    const c = useCommands({ base: "", selected: ref(null), operator: () => false, span: () => span });
    c.tick(span[0]);
    await settle();
    expect(reads.length).toBe(1);
    span = [now - 80_000_000, now - 7_200_000]; // zoomed in: inside what was read
    c.tick(span[0]);
    await settle();
    expect(reads.length).toBe(1);
    span = [now - 2 * 86_400_000, now - 3_600_000]; // zoomed out: earlier than was read
    c.tick(span[0]);
    await settle();
    expect(reads.length).toBe(2);
    expect(reads[1]).toContain(`to=${now - 3_600_000}`);
  });

  it("are read again for a span inside a read cut at the API's limit", async () => {
    const now = Date.now();
    const reads = counting(Array.from({ length: 1_000 }, (_, i) => cmd(`c${i}`, "pause", now - 80_000_000 + i)));
    let span: [number, number] = [now - 86_400_000, now - 3_600_000];
    const c = useCommands({ base: "", selected: ref(null), operator: () => false, span: () => span });
    c.tick(span[0]);
    await settle();
    span = [now - 80_000_000, now - 7_200_000];
    c.tick(span[0]);
    await settle();
    expect(reads.length).toBe(2);
  });
});
