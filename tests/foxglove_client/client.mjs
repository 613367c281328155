// An independent Foxglove WebSocket client for the integration tests: Foxglove's own npm
// client (@foxglove/ws-protocol) connects, subscribes to every channel the server advertises,
// decodes each message with the schema the server sent (protobuf: its FileDescriptorSet; JSON:
// its JSON schema) and checks it: a protobuf message of a Foxglove schema against that schema
// as @foxglove/schemas publishes it, a JSON message against the channel's own JSON schema.
// It prints one JSON line per event on stdout and takes commands as JSON lines on stdin:
//   {"op": "playback", "command": "play" | "pause", "speed": 1, "seek_ms": 123 | null}
//   {"op": "close"}
// Usage: node client.mjs URL [--token T] [--origin O] [--host H]
import { createHash } from "node:crypto";
import { createInterface } from "node:readline";

import wsProtocol from "@foxglove/ws-protocol";
import foxgloveSchemas from "@foxglove/schemas/jsonschema.js";
import Ajv from "ajv";
import protobuf from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import WebSocket from "ws";

import { decodePlaybackState, encodePlaybackRequest } from "./playback.mjs";

const { FoxgloveClient } = wsProtocol; // a CommonJS package

const args = process.argv.slice(2);
const url = args[0];
const option = (name) => {
  const i = args.indexOf(name);
  return i >= 0 ? args[i + 1] : undefined;
};
const headers = {};
if (option("--token")) headers.Authorization = `Bearer ${option("--token")}`;
if (option("--origin")) headers.Origin = option("--origin");
if (option("--host")) headers.Host = option("--host");

// BigInt (nanosecond times) as numbers: a JSON line has no BigInt.
const out = (event) =>
  process.stdout.write(
    JSON.stringify(event, (_k, v) => (typeof v === "bigint" ? Number(v) : v)) + "\n",
  );
const ajv = new Ajv({ strict: false, allErrors: true });
// @foxglove/schemas' JSON schemas by their schema name (foxglove.Grid, ...).
const foxgloveValidators = new Map();
for (const schema of Object.values(foxgloveSchemas)) {
  if (schema && typeof schema === "object" && typeof schema.title === "string") {
    foxgloveValidators.set(schema.title, ajv.compile(schema));
  }
}

const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL], { headers });
ws.on("unexpected-response", (_req, res) => {
  let body = "";
  res.on("data", (d) => (body += d));
  res.on("end", () => {
    out({ event: "refused", status: res.statusCode, body });
    process.exit(0);
  });
});
const client = new FoxgloveClient({ ws });
const channels = new Map(); // channel id -> {topic, schemaName, decode, validate}
const subscriptions = new Map(); // subscription id -> channel id

function b64bytes(text) {
  return Uint8Array.from(Buffer.from(text, "base64"));
}

// A protobuf object as Foxglove's JSON schemas describe it: time as {sec, nsec}.
function asFoxgloveJson(value) {
  if (Array.isArray(value)) return value.map(asFoxgloveJson);
  if (value && typeof value === "object") {
    const keys = Object.keys(value);
    if (keys.length === 2 && "seconds" in value && "nanos" in value) {
      return { sec: Number(value.seconds), nsec: Number(value.nanos) };
    }
    return Object.fromEntries(keys.map((k) => [k, asFoxgloveJson(value[k])]));
  }
  return value;
}

function channelCodec(channel) {
  if (channel.encoding === "protobuf") {
    const set = descriptor.FileDescriptorSet.decode(b64bytes(channel.schema));
    const type = protobuf.Root.fromDescriptor(set).lookupType(channel.schemaName);
    const check = foxgloveValidators.get(channel.schemaName);
    return {
      decode: (bytes) =>
        asFoxgloveJson(
          type.toObject(type.decode(bytes), {
            longs: Number,
            enums: Number,
            bytes: String,
            defaults: true,
            arrays: true,
          }),
        ),
      validate: check,
      known: Boolean(check),
    };
  }
  if (channel.encoding === "json") {
    const check = ajv.compile({ ...JSON.parse(channel.schema), $schema: undefined });
    return {
      decode: (bytes) => JSON.parse(Buffer.from(bytes).toString("utf8")),
      validate: check,
      known: true,
    };
  }
  return { decode: () => null, validate: null, known: false };
}

// What the tests compare: the grid's pixels by digest, not as base64.
function summary(schemaName, msg) {
  if (schemaName === "foxglove.Grid" && typeof msg.data === "string") {
    const data = Buffer.from(msg.data, "base64");
    return { ...msg, data: undefined, data_sha256: createHash("sha256").update(data).digest("hex"), data_len: data.length };
  }
  return msg;
}

client.on("open", () => out({ event: "open" }));
client.on("serverInfo", (info) =>
  out({
    event: "serverInfo",
    name: info.name,
    capabilities: info.capabilities,
    dataStartTime: info.dataStartTime ?? null,
    dataEndTime: info.dataEndTime ?? null,
  }),
);
client.on("status", (status) => out({ event: "status", level: status.level, message: status.message }));
client.on("error", (error) => out({ event: "error", message: String(error?.message ?? error) }));
client.on("close", (ev) => {
  out({ event: "close", code: ev?.code ?? null, reason: String(ev?.reason ?? "") });
  process.exit(0);
});
client.on("advertise", (advertised) => {
  for (const channel of advertised) {
    let codec;
    try {
      codec = channelCodec(channel);
    } catch (error) {
      out({ event: "badSchema", topic: channel.topic, schema: channel.schemaName, error: String(error) });
      continue;
    }
    channels.set(channel.id, { topic: channel.topic, schemaName: channel.schemaName, ...codec });
    subscriptions.set(client.subscribe(channel.id), channel.id);
    out({ event: "advertise", topic: channel.topic, schema: channel.schemaName, encoding: channel.encoding, known: codec.known });
  }
});
client.on("unadvertise", (ids) => out({ event: "unadvertise", ids }));
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const channel = channels.get(subscriptions.get(subscriptionId));
  if (!channel) return;
  const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  let msg;
  try {
    msg = channel.decode(bytes);
  } catch (error) {
    out({ event: "message", topic: channel.topic, schema: channel.schemaName, valid: false, errors: [String(error)] });
    return;
  }
  const valid = channel.validate ? channel.validate(msg) : false;
  out({
    event: "message",
    topic: channel.topic,
    schema: channel.schemaName,
    log_ms: Number(BigInt(timestamp) / 1000000n),
    received_ms: Date.now(),
    valid,
    errors: valid ? undefined : channel.validate?.errors ?? ["no schema to check it against"],
    msg: summary(channel.schemaName, msg),
  });
});
// Playback control, by the npm client where it has it, else encoded and read as the
// protocol defines them (playback.mjs).
const nativePlayback = typeof client.sendPlaybackControlRequest === "function";
const playbackState = (state) =>
  out({
    event: "playbackState",
    status: state.status,
    current_ms: Number(BigInt(state.currentTime ?? 0) / 1000000n),
    speed: state.playbackSpeed,
    did_seek: state.didSeek,
    request_id: state.requestId ?? null,
  });
if (nativePlayback) {
  client.on("playbackState", playbackState);
} else {
  ws.on("message", (raw, isBinary) => {
    const state = decodePlaybackState(raw, isBinary);
    if (state) playbackState(state);
  });
}

function sendPlayback(request) {
  if (nativePlayback) {
    client.sendPlaybackControlRequest(request);
    return;
  }
  ws.send(encodePlaybackRequest(request));
}
client.on("time", ({ timestamp }) => out({ event: "time", at_ms: Number(BigInt(timestamp) / 1000000n) }));

let requests = 0;
createInterface({ input: process.stdin }).on("line", (line) => {
  const command = JSON.parse(line);
  if (command.op === "close") {
    client.close();
  } else if (command.op === "playback") {
    requests += 1;
    sendPlayback({
      playbackCommand: command.command === "play" ? 0 : 1,
      playbackSpeed: command.speed ?? 1,
      seekTime: command.seek_ms == null ? undefined : BigInt(command.seek_ms) * 1000000n,
      requestId: `r${requests}`,
    });
  }
});
