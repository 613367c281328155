import { describe, expect, it } from "vitest";
import { conflictKey, exportUrl, fileNameOf, gapText, sizeText, type ConflictEntry } from "../src/lib/inspect";

const c: ConflictEntry = {
  row: 3, column: 4, ts_ms: 1_000_12_345, robot_a: "a", ts_a_ms: 1_000_00_000, hash_a: "aa", robot_b: "b", hash_b: "bb", seek_ms: 1_000_12_346,
};

describe("inspect", () => {
  it("says how far apart the two writes were, in seconds", () => {
    expect(gapText(c)).toBe("12.3 s");
    expect(conflictKey(c)).toBe("100012345:3:4:b");
  });

  it("asks for the span as MCAP or as an analysts' view in CSV, in whole milliseconds", () => {
    expect(exportUrl("", "mcap", 10.4, 20.2)).toBe("/api/v1/exports/replay.mcap?from=10&to=21");
    expect(exportUrl("http://h", "chunk-changes", 10, 20)).toBe("http://h/api/v1/exports/tables/chunk-changes?from=10&to=20&format=csv");
  });

  it("names the file as the server does", () => {
    const r = new Response("", { headers: { "Content-Disposition": 'attachment; filename="replay-1-2.mcap"' } });
    expect(fileNameOf(r, "x")).toBe("replay-1-2.mcap");
    expect(fileNameOf(new Response(""), "fallback.csv")).toBe("fallback.csv");
  });

  it("gives sizes with units", () => {
    expect(sizeText(512)).toBe("512 B");
    expect(sizeText(2048)).toBe("2.0 kB");
    expect(sizeText(13_500_000)).toBe("12.9 MB");
  });
});
