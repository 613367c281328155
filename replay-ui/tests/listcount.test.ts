import { describe, expect, it } from "vitest";
import { listCountText } from "../src/lib/listcount";

describe("a list's count in words", () => {
  it("is the count when the list is whole, and says 'at least' (never 'N+') when more is unread", () => {
    for (let n = 0; n < 300; n++) {
      const whole = listCountText(n, false, "floor change", "floor changes", "the newest");
      expect(whole).toBe(`${n} floor change${n === 1 ? "" : "s"}`);
      const part = listCountText(n, true, "floor change", "floor changes", "the newest");
      expect(part).toBe(`at least ${n} floor changes (the newest)`);
      expect(part).not.toMatch(/\d\+/);
    }
  });
});
