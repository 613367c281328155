// `mapservice bench foxglove`'s clients: Foxglove's own npm client (@foxglove/ws-protocol),
// the one the integration test drives through client.mjs, here without decoding or checking
// each message (client.mjs does that, one JSON line a message: at thousands of messages a
// second the printing would be the bench's limit, not the server). Commands come as JSON
// lines on stdin, results go out as JSON lines on stdout.
//
//   node bench.mjs live URL --clients K [--pose-prefix P]
//     K clients, each subscribed to every channel the server advertises (robots' channels
//     as they appear). Counts messages and bytes per client; for each pose of a robot whose
//     id starts with P, the delivery latency: receipt (Date.now()) minus the message's log
//     time (the pose's own timestamp, which the bench fleet sets to the wall clock as it
//     publishes; each pose's log time is reported too). {"op": "start"} zeroes the counts, {"op": "stop"} prints them
//     ({"event": "report", ...}); every 2 s a {"event": "progress"} line.
//   node bench.mjs seek URL [--quiet-ms Q]
//     One client with the playback-control capability. {"op": "seek", "at_ms": T} pauses
//     with a seek to T and times from the request the seek's answer, the floor (/map logged
//     at T) and each robot's first pose; once the floor and a pose came and nothing more for
//     Q ms, {"event": "seek", ...} (the caller knows which robots stand at T: the frame is
//     complete when the floor and each of theirs arrived).
import { createInterface } from "node:readline";
import { performance } from "node:perf_hooks";

import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

import { decodePlaybackState, encodePlaybackRequest } from "./playback.mjs";

const { FoxgloveClient } = wsProtocol; // a CommonJS package

const [mode, url, ...rest] = process.argv.slice(2);
const option = (name, fallback) => {
  const i = rest.indexOf(name);
  return i >= 0 ? rest[i + 1] : fallback;
};
const out = (event) => process.stdout.write(JSON.stringify(event) + "\n");
const POSE = /^\/robots\/(.+)\/pose$/;
const NS_PER_MS = 1000000n;

// One connection; `onMessage(topic, logMs, bytes)` for each message of every channel.
function connect(index, onMessage, onInfo) {
  const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
  const client = new FoxgloveClient({ ws });
  const topics = new Map(); // subscription id -> topic
  const state = { open: false, closed: null, client, ws };
  ws.on("unexpected-response", (_req, res) => {
    state.closed = `refused ${res.statusCode}`;
    out({ event: "closed", client: index, reason: state.closed });
  });
  client.on("open", () => (state.open = true));
  client.on("serverInfo", (info) => onInfo?.(info));
  client.on("error", (error) => out({ event: "error", client: index, message: String(error?.message ?? error) }));
  client.on("close", (ev) => {
    state.closed = `${ev?.code ?? ""} ${ev?.reason ?? ""}`;
    out({ event: "closed", client: index, reason: state.closed });
  });
  // The server's errors (an "Unknown channel ID" answer to a subscription among them).
  client.on("status", (s) => {
    if (s.level >= 2) out({ event: "status", client: index, level: s.level, message: s.message });
  });
  client.on("advertise", (channels) => {
    for (const channel of channels) topics.set(client.subscribe(channel.id), channel.topic);
  });
  client.on("message", ({ subscriptionId, timestamp, data }) => {
    const topic = topics.get(subscriptionId);
    if (topic !== undefined) onMessage(topic, Number(BigInt(timestamp) / NS_PER_MS), data.byteLength);
  });
  return state;
}

function live() {
  const clients = Number(option("--clients", "10"));
  const prefix = option("--pose-prefix", "");
  const fresh = () => ({ messages: 0, bytes: 0, poses: 0, latencies: [], pose_log_ms: [] });
  const counts = Array.from({ length: clients }, fresh);
  const states = counts.map((count, i) =>
    connect(i, (topic, logMs, bytes) => {
      count.messages += 1;
      count.bytes += bytes;
      const pose = POSE.exec(topic);
      if (pose && pose[1].startsWith(prefix)) {
        count.poses += 1;
        count.latencies.push(Date.now() - logMs);
        count.pose_log_ms.push(logMs);
      }
    }),
  );
  let since = performance.now();
  const zero = () => {
    for (const c of counts) Object.assign(c, fresh());
    since = performance.now();
  };
  setInterval(
    () =>
      out({
        event: "progress",
        connected: states.filter((s) => s.open && s.closed === null).length,
        seconds: (performance.now() - since) / 1000,
        messages: counts.map((c) => c.messages),
      }),
    2000,
  ).unref();
  return (command) => {
    if (command.op === "start") zero();
    if (command.op === "stop") {
      out({
        event: "report",
        seconds: (performance.now() - since) / 1000,
        clients: counts.map((c, i) => ({ ...c, closed: states[i].closed })),
      });
    }
    if (command.op === "close") {
      for (const s of states) s.client.close();
      process.exit(0);
    }
  };
}

function seek() {
  const quietMs = Number(option("--quiet-ms", "1000"));
  let pending = null; // the seek being timed
  let requests = 0;
  const state = connect(
    0,
    (topic, logMs) => {
      if (!pending) return;
      const now = performance.now();
      pending.last = now;
      if (topic === "/map" && logMs === pending.atMs && pending.grid === null) {
        pending.grid = now - pending.t0;
      }
      const pose = POSE.exec(topic);
      if (pose && !(pose[1] in pending.poses)) pending.poses[pose[1]] = now - pending.t0;
    },
    (info) =>
      out({
        event: "serverInfo",
        capabilities: info.capabilities,
        start_ms: info.dataStartTime ? Number(info.dataStartTime.sec) * 1000 : null,
        end_ms: info.dataEndTime ? Number(info.dataEndTime.sec) * 1000 : null,
      }),
  );
  state.ws.on("message", (raw, isBinary) => {
    const s = decodePlaybackState(raw, isBinary);
    if (s && pending && s.didSeek && s.requestId === pending.id && pending.answer === null) {
      pending.answer = performance.now() - pending.t0;
    }
  });
  // A seek's messages are over once the floor and a pose came and then nothing for quietMs.
  setInterval(() => {
    if (!pending || pending.grid === null || Object.keys(pending.poses).length === 0) return;
    if (performance.now() - pending.last < quietMs) return;
    out({
      event: "seek",
      at_ms: pending.atMs,
      answer_ms: pending.answer,
      grid_ms: pending.grid,
      poses: pending.poses,
    });
    pending = null;
  }, 50).unref();
  return (command) => {
    if (command.op === "seek") {
      requests += 1;
      const id = `seek${requests}`;
      const t0 = performance.now();
      pending = { id, atMs: command.at_ms, poses: {}, grid: null, answer: null, t0, last: t0 };
      state.ws.send(
        encodePlaybackRequest({
          playbackCommand: 1, // pause
          playbackSpeed: 1,
          seekTime: BigInt(command.at_ms) * NS_PER_MS,
          requestId: id,
        }),
      );
    }
    if (command.op === "close") {
      state.client.close();
      process.exit(0);
    }
  };
}

const handle = mode === "live" ? live() : mode === "seek" ? seek() : null;
if (!handle) {
  process.stderr.write("usage: node bench.mjs live|seek URL [--clients K] [--pose-prefix P]\n");
  process.exit(2);
}
createInterface({ input: process.stdin }).on("line", (line) => handle(JSON.parse(line)));
