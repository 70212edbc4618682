// Read an MCAP file with the reference TypeScript reader (@mcap/core), not the Python
// library truckd writes it with: print one JSON object with the header, the channels and
// schemas, the summary's statistics and every message decoded (JSON), per topic.
// Usage: node mcap_read.mjs FILE
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { decompress } from "fzstd";

const file = await open(process.argv[2], "r");
const size = (await file.stat()).size;
const readable = {
  size: async () => BigInt(size),
  read: async (offset, length) => {
    const buf = new Uint8Array(Number(length));
    await file.read(buf, 0, Number(length), Number(offset));
    return buf;
  },
};
const reader = await McapIndexedReader.Initialize({
  readable,
  decompressHandlers: { zstd: (data) => decompress(data) },
});
const text = new TextDecoder("utf-8", { fatal: true });
const out = {
  profile: reader.header.profile,
  library: reader.header.library,
  schemas: {},
  channels: {},
  statistics: null,
  metadata: {},
  messages: {},
};
for (const [id, s] of reader.schemasById) {
  out.schemas[id] = { name: s.name, encoding: s.encoding, data: text.decode(s.data) };
}
for (const [id, c] of reader.channelsById) {
  out.channels[id] = {
    topic: c.topic,
    messageEncoding: c.messageEncoding,
    schemaId: c.schemaId,
  };
  out.messages[c.topic] = [];
}
if (reader.statistics) {
  const st = reader.statistics;
  out.statistics = {
    messageCount: Number(st.messageCount),
    channelMessageCounts: Object.fromEntries(
      [...st.channelMessageCounts].map(([k, v]) => [k, Number(v)]),
    ),
  };
}
for (const idx of reader.metadataIndexes) {
  for await (const m of reader.readMetadata({ name: idx.name })) {
    out.metadata[m.name] = Object.fromEntries(m.metadata);
  }
}
for await (const m of reader.readMessages()) {
  const topic = reader.channelsById.get(m.channelId).topic;
  out.messages[topic].push({
    logTime: m.logTime.toString(),
    sequence: m.sequence,
    data: JSON.parse(text.decode(m.data)),
  });
}
await file.close();
process.stdout.write(JSON.stringify(out));
