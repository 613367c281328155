import { EventEmitter } from "node:events";
import { describe, expect, it } from "vitest";
import type { MqttClient } from "mqtt";
import { poseMessage } from "../src/lib/legacy";
import { RobotLink, refusedCredential } from "../src/lib/robotlink";
import type { ClientConfig } from "../src/lib/robotlink";

const CONFIG: ClientConfig = { mqtt_ws_url: "ws://127.0.0.1:9001/mqtt", coordinate_topic_prefix: "iot/coordinates/", create_chunk_topic: "iot/chunks/create", robot_chunk_topic_prefix: "iot/chunks/create/" };

class FakeClient extends EventEmitter {
  sent: [string, string, { qos: number }][] = [];
  ended = false;
  publish(topic: string, payload: string, opts: { qos: number }) {
    this.sent.push([topic, payload, opts]);
  }
  end() {
    this.ended = true;
  }
}

function linked(config = CONFIG) {
  const fake = new FakeClient();
  const calls: [string, object][] = [];
  const link = new RobotLink(config, () => {}, (url, opts) => {
    calls.push([url, opts]);
    return fake as unknown as MqttClient;
  });
  return { fake, calls, link };
}

describe("RobotLink", () => {
  it("connects to the configured WebSocket URL and publishes the 2019 pose on iot/coordinates/{robotId}", () => {
    const { fake, calls, link } = linked();
    link.start("page-1");
    expect(calls[0][0]).toBe("ws://127.0.0.1:9001/mqtt");
    expect(link.state).toBe("connecting");
    fake.emit("connect");
    expect(link.state).toBe("connected");
    const pose = poseMessage("r7", 1.5, -2, 0, Date.UTC(2018, 11, 20, 23, 34, 33), 80);
    expect(link.publishPose("r7", pose)).toBe(true);
    const [topic, payload, opts] = fake.sent[0];
    expect(topic).toBe("iot/coordinates/r7");
    expect(opts.qos).toBe(1);
    expect(JSON.parse(payload)).toEqual({
      robotId: "r7",
      timestamp: "2018-12-20T23:34:33",
      pose: { position: { x: 1.5, y: -2, z: 0 }, orientation: { x: 0, y: 0, z: 0, w: 1 } },
      status: { battery: { battery_level: 80, charging: false }, loaded: false },
    });
  });

  it("drops poses while not connected and reports reconnects", () => {
    const { fake, link } = linked();
    link.start("page-1");
    expect(link.publishPose("r7", {})).toBe(false);
    fake.emit("connect");
    fake.emit("close");
    expect(link.state).toBe("offline");
    fake.emit("reconnect");
    expect(link.state).toBe("reconnecting");
    expect(link.publishChunk("r7", {})).toBe(false);
    fake.emit("error", new Error("connection refused"));
    expect(link.error).toBe("connection refused");
    fake.emit("connect");
    expect(link.publishChunk("r7", { row: 1 })).toBe(true);
    expect(fake.sent.map((m) => m[0])).toEqual(["iot/chunks/create/r7"]);
    expect(link.error).toBe("");
  });

  it("publishes chunks on the 2019 topic where the gateway reads no per-robot chunk topic", () => {
    const { fake, link } = linked({ ...CONFIG, robot_chunk_topic_prefix: null });
    link.start("page-1");
    fake.emit("connect");
    expect(link.publishChunk("r7", { row: 1 })).toBe(true);
    expect(fake.sent.map((m) => m[0])).toEqual(["iot/chunks/create"]);
  });

  it("connects with a robot's credential when given one, anonymously otherwise", () => {
    const anonymous = linked();
    anonymous.link.start("page-1");
    expect(anonymous.calls[0][1]).not.toHaveProperty("username");
    const robot = linked();
    robot.link.start("page-1", { username: "r7", password: "s3cret" });
    expect(robot.calls[0][1]).toMatchObject({ username: "r7", password: "s3cret" });
  });

  it("recognises a broker refusing the credential", () => {
    expect(refusedCredential("Connection refused: Not authorized")).toBe(true);
    expect(refusedCredential("Connection refused: Bad User Name or Password")).toBe(true);
    expect(refusedCredential("connection refused")).toBe(false);
  });

  it("without a WebSocket URL is unconfigured and never connects", () => {
    const { calls, link } = linked({ ...CONFIG, mqtt_ws_url: null });
    link.start("page-1");
    expect(link.state).toBe("unconfigured");
    expect(calls).toHaveLength(0);
    expect(link.publishPose("r7", {})).toBe(false);
  });
});
