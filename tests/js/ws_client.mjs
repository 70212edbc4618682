// Connect to a Foxglove WebSocket server with the reference client (@foxglove/ws-protocol,
// its default subprotocol foxglove.websocket.v1, over the `ws` package), subscribe to the
// topics asked for and decode their JSON messages; print one JSON object: the subprotocol
// agreed, serverInfo, the channels advertised, and per topic the messages received.
// Usage: node ws_client.mjs URL MIN_PER_TOPIC TIMEOUT_S TOPIC...
// Ends when every topic has MIN_PER_TOPIC messages, or after TIMEOUT_S (exit code 3).
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, minArg, timeoutArg, ...topics] = process.argv.slice(2);
const want = Number(minArg);
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const text = new TextDecoder("utf-8", { fatal: true });
const out = {
  requested: FoxgloveClient.SUPPORTED_SUBPROTOCOL,
  subprotocol: null,
  serverInfo: null,
  channels: {},
  messages: Object.fromEntries(topics.map((t) => [t, []])),
  errors: [],
};
const subs = new Map(); // subscription id -> topic

let finished = false;
function done(code) {
  if (finished) return;
  finished = true;
  clearTimeout(timer);
  client.close();
  // exit only once stdout is flushed (a pipe takes 64 kB at a time)
  process.stdout.write(JSON.stringify(out), () => process.exit(code));
}
const timer = setTimeout(() => done(3), Number(timeoutArg) * 1000);

client.on("open", () => {
  out.subprotocol = ws.protocol;
});
client.on("error", (e) => {
  out.errors.push(String(e && e.message ? e.message : e));
  done(4);
});
client.on("serverInfo", (info) => {
  out.serverInfo = info;
});
client.on("advertise", (channels) => {
  for (const c of channels) {
    out.channels[c.topic] = c;
    if (topics.includes(c.topic)) subs.set(client.subscribe(c.id), c.topic);
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = subs.get(subscriptionId);
  const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  out.messages[topic].push({ logTime: timestamp.toString(), data: JSON.parse(text.decode(bytes)) });
  if (topics.every((t) => out.messages[t].length >= want)) done(0);
});
