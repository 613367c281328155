/**
 * The controller page's MQTT connection, over WebSocket (browsers have no raw TCP): it
 * publishes on the same 2019 topics as a robot, so the gateway cannot tell them apart.
 * The broker's URL and the topics come from the API (`GET /api/v1/client-config`).
 */
import mqtt from "mqtt";
import type { IClientOptions, MqttClient } from "mqtt";
import { getJson } from "./request";

export interface ClientConfig {
  mqtt_ws_url: string | null;
  coordinate_topic_prefix: string;
  create_chunk_topic: string;
  robot_chunk_topic_prefix: string | null;
}

/** A robot's MQTT credential (its username is its robotId), where the broker checks them. */
export interface RobotCredential {
  username: string;
  password: string;
}

/** mqtt.js's words for a refused CONNECT (MQTT 3.1.1 codes 4 and 5, MQTT 5 0x86, 0x87). */
export function refusedCredential(error: string): boolean {
  return /not authori[sz]ed|bad user ?name or password/i.test(error);
}

export type LinkState = "unconfigured" | "connecting" | "connected" | "reconnecting" | "offline";

export type Connect = (url: string, options: IClientOptions) => MqttClient;

/** Where the broker is and on which topics a robot publishes, through the page's request
 * layer (its session, a busy server waited for); a failure is an ApiError in a user's words. */
export function getClientConfig(base = ""): Promise<ClientConfig> {
  return getJson<ClientConfig>(`${base}/api/v1/client-config`, "the robot link's settings");
}

export class RobotLink {
  state: LinkState;
  error = "";
  published = 0;
  private client: MqttClient | null = null;

  constructor(
    private config: ClientConfig,
    private onChange: (link: RobotLink) => void = () => {},
    private connect: Connect = mqtt.connect,
  ) {
    this.state = config.mqtt_ws_url ? "offline" : "unconfigured";
  }

  start(clientId: string, credential?: RobotCredential): void {
    if (!this.config.mqtt_ws_url || this.client) return;
    this.set("connecting", "");
    // mqtt.js reconnects on its own; 2 s keeps the page's pose flowing soon after a broker restart.
    const options: IClientOptions = { clientId, reconnectPeriod: 2000, connectTimeout: 5000, clean: true };
    if (credential?.password) Object.assign(options, credential);
    const c = this.connect(this.config.mqtt_ws_url, options);
    this.client = c;
    c.on("connect", () => this.set("connected", ""));
    c.on("reconnect", () => this.set("reconnecting"));
    c.on("offline", () => this.set("offline"));
    c.on("close", () => {
      if (this.state === "connected") this.set("offline");
    });
    c.on("error", (e: Error) => this.set(this.state, e.message));
  }

  stop(): void {
    this.client?.end(true);
    this.client = null;
    if (this.state !== "unconfigured") this.set("offline");
  }

  /** iot/coordinates/{robotId}: dropped while disconnected (a stale pose is worth nothing). */
  publishPose(robotId: string, message: object): boolean {
    return this.publish(this.config.coordinate_topic_prefix + robotId, message);
  }

  /** The body of POST /api/chunk-service/chunks, on the robot's own chunk topic
   *  (iot/chunks/create/{robotId}, which a broker's ACL ties to its username) or, where the
   *  gateway reads none, on the 2019 iot/chunks/create. */
  publishChunk(robotId: string, message: object): boolean {
    const prefix = this.config.robot_chunk_topic_prefix;
    return this.publish(prefix ? prefix + robotId : this.config.create_chunk_topic, message);
  }

  private publish(topic: string, message: object): boolean {
    if (!this.client || this.state !== "connected") return false;
    // QoS 1 as the 2019 robots: the gateway acknowledges only once Kafka has the message.
    this.client.publish(topic, JSON.stringify(message), { qos: 1 });
    this.published++;
    this.onChange(this);
    return true;
  }

  private set(state: LinkState, error?: string): void {
    this.state = state;
    if (error !== undefined) this.error = error;
    this.onChange(this);
  }
}
