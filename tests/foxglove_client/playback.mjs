// The protocol's playback control as its spec defines the binary messages (client opcode 3,
// server opcode 5), for an npm client that has no playback API of its own (0.8.0 has none).

// A playback control request's bytes: {playbackCommand: 0 play | 1 pause, playbackSpeed,
// seekTime (bigint ns) or undefined, requestId}.
export function encodePlaybackRequest(request) {
  const id = Buffer.from(request.requestId, "utf8");
  const buffer = Buffer.alloc(1 + 1 + 4 + 1 + 8 + 4 + id.length);
  buffer.writeUInt8(3, 0);
  buffer.writeUInt8(request.playbackCommand, 1);
  buffer.writeFloatLE(request.playbackSpeed, 2);
  buffer.writeUInt8(request.seekTime === undefined ? 0 : 1, 6);
  buffer.writeBigUInt64LE(request.seekTime ?? 0n, 7);
  buffer.writeUInt32LE(id.length, 15);
  id.copy(buffer, 19);
  return buffer;
}

// A server's binary message as a playback state, or null if it is another message.
export function decodePlaybackState(raw, isBinary) {
  const data = raw instanceof ArrayBuffer ? Buffer.from(raw) : raw;
  if (!isBinary || data[0] !== 5) return null;
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const idLength = view.getUint32(15, true);
  return {
    status: view.getUint8(1),
    currentTime: view.getBigUint64(2, true),
    playbackSpeed: view.getFloat32(10, true),
    didSeek: view.getUint8(14) !== 0,
    requestId: Buffer.from(data.subarray(19, 19 + idLength)).toString("utf8"),
  };
}
