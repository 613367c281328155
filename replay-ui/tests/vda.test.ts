import { describe, expect, it } from "vitest";
import { connectionAt, errorMarks, errorsAt, factsheetSummary, isVehicleId, type VdaVehicle } from "../src/lib/vda";

const bumper = { level: "FATAL", type: "bumper", description: "hit" };
const battery = { level: "WARNING", type: "lowBattery", description: "charge me" };

function vehicle(over: Partial<VdaVehicle> = {}): VdaVehicle {
  return {
    robotId: "Acme:1", manufacturer: "Acme", serialNumber: "1", online: null,
    errors: [
      { ts_ms: 2000, ...battery }, { ts_ms: 3000, ...battery }, { ts_ms: 3000, ...bumper },
      { ts_ms: 6000, ...bumper },
    ],
    connections: [{ ts_ms: 1000, state: "ONLINE", sent_ms: 1000 }, { ts_ms: 8000, state: "CONNECTIONBROKEN", sent_ms: 1000 }],
    factsheet: null, errorClears: [4000], ...over,
  };
}

describe("VDA 5050 facts", () => {
  it("marks each error where it begins, again after a clear", () => {
    const marks = errorMarks([vehicle()]);
    expect(marks.map((m) => [m.ts_ms, m.type])).toEqual([[2000, "lowBattery"], [3000, "bumper"], [6000, "bumper"]]);
    expect(marks[0].robotId).toBe("Acme:1");
  });

  it("holds a state's errors until the next state, fatal first, none after a clear", () => {
    const v = vehicle();
    expect(errorsAt(v, 1999)).toEqual([]);
    expect(errorsAt(v, 2500).map((e) => e.type)).toEqual(["lowBattery"]);
    expect(errorsAt(v, 3500).map((e) => e.type)).toEqual(["bumper", "lowBattery"]);
    expect(errorsAt(v, 4000)).toEqual([]);
    expect(errorsAt(v, 7000).map((e) => e.type)).toEqual(["bumper"]);
    expect(errorsAt(undefined, 7000)).toEqual([]);
  });

  it("takes the connection state at or before the instant", () => {
    expect(connectionAt(vehicle(), 500)).toBeNull();
    expect(connectionAt(vehicle(), 7999)?.state).toBe("ONLINE");
    expect(connectionAt(vehicle(), 8000)?.state).toBe("CONNECTIONBROKEN");
  });

  it("summarises the factsheet", () => {
    const v = vehicle({ factsheet: { ts_ms: 1, vda_version: "2.1.0", factsheet: {
      manufacturer: "Acme", serialNumber: "1", typeSpecification: { seriesName: "Tugger 3" }, physicalParameters: { speedMax: 1.8 } } } });
    expect(factsheetSummary(v)).toEqual({ manufacturer: "Acme", serialNumber: "1", series: "Tugger 3", speedMax: 1.8, version: "2.1.0" });
    expect(factsheetSummary(vehicle())).toBeNull();
    expect(isVehicleId("Acme@20Co:7@3A1")).toBe(true);
    expect(isVehicleId("sim-001")).toBe(false);
  });
});
