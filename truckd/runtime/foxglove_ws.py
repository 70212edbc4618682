"""A Foxglove WebSocket server of our own on the published protocol (the ``websockets``
package): what ``truckd monitor --foxglove`` serves.

The protocol (github.com/foxglove/ws-protocol, docs/spec.md) under both of its
subprotocol names: ``foxglove.websocket.v1`` (the reference client ``@foxglove/ws-protocol``
and every viewer and bridge built on it) and ``foxglove.sdk.v1`` (the same messages under
the name foxglove-sdk 0.30 and recent Foxglove use).  The subset a live JSON source needs:

- server -> client, text: ``serverInfo`` on connect, ``advertise`` (every channel open
  when a client connects, then each new one), ``unadvertise``, ``status`` (a refused
  request);
- client -> server, text: ``subscribe``, ``unsubscribe`` (anything else is answered with
  a ``status`` warning and ignored);
- server -> client, binary: message data = opcode 0x01, subscription id (uint32 LE),
  log time (uint64 LE, ns), payload.

Each connection has a bounded send queue emptied by its own thread: a slow viewer loses
its oldest messages (counted in ``dropped``), never delays the publisher.
"""

from __future__ import annotations

import json
import logging
import queue
import struct
import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from websockets.sync.server import Server, ServerConnection

log = logging.getLogger("truckd.foxglove")

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
"""Accepted, in the server's order of preference (one protocol, two names)."""

OP_MESSAGE_DATA = 0x01
_HEADER = struct.Struct("<BIQ")
QUEUE_LEN = 1024
"""Frames waiting for one client; beyond that the oldest is dropped."""


@dataclass(frozen=True)
class WsChannel:
    """An advertised channel (the spec's Channel object)."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema: str
    schema_encoding: str

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "topic": self.topic,
            "encoding": self.encoding,
            "schemaName": self.schema_name,
            "schema": self.schema,
            "schemaEncoding": self.schema_encoding,
        }


@dataclass
class _Client:
    conn: ServerConnection
    out: queue.Queue[str | bytes | None] = field(
        default_factory=lambda: queue.Queue(maxsize=QUEUE_LEN)
    )
    subs: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id
    dropped: int = 0

    def put(self, frame: str | bytes | None) -> None:
        while True:
            try:
                self.out.put_nowait(frame)
                return
            except queue.Full:
                try:
                    self.out.get_nowait()  # the oldest goes
                    self.dropped += 1
                except queue.Empty:
                    pass


class FoxgloveServer:
    """The server: ``start()`` (returns the port bound), ``add_channel``,
    ``remove_channel``, ``log``, ``stop()``.  Thread-safe."""

    def __init__(self, name: str = "truckd", host: str = "127.0.0.1", port: int = 0) -> None:
        self.name = name
        self.host = host
        self.port = port
        self._server: Server | None = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._channels: dict[int, WsChannel] = {}
        self._clients: list[_Client] = []
        self._next_id = 1
        self.dropped = 0
        """Frames dropped for slow clients (all clients, ever)."""

    # -- lifecycle ---------------------------------------------------------------------
    def start(self) -> int:
        """Listen and serve on a thread; the port bound.  Raises OSError (port taken)."""
        from websockets.sync.server import serve

        self._server = serve(
            self._handle,
            self.host,
            self.port,
            subprotocols=list(SUBPROTOCOLS),  # type: ignore[arg-type]
            compression=None,
        )
        self.port = int(self._server.socket.getsockname()[1])
        self._thread = threading.Thread(
            target=self._server.serve_forever, name="foxglove-ws", daemon=True
        )
        self._thread.start()
        return self.port

    def stop(self) -> None:
        """Close every connection and stop listening (idempotent)."""
        server, self._server = self._server, None
        if server is None:
            return
        server.shutdown()
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.put(None)
            c.conn.close()
        if self._thread is not None:
            self._thread.join(timeout=5)

    # -- channels and messages ---------------------------------------------------------
    def add_channel(
        self, topic: str, encoding: str, schema_name: str, schema: bytes, schema_encoding: str
    ) -> int:
        """Advertise a channel to every client (now and later); its id."""
        with self._lock:
            ch = WsChannel(
                self._next_id, topic, encoding, schema_name, schema.decode(), schema_encoding
            )
            self._next_id += 1
            self._channels[ch.id] = ch
            frame = json.dumps({"op": "advertise", "channels": [ch.as_dict()]})
            for c in self._clients:
                c.put(frame)
        return ch.id

    def remove_channel(self, channel_id: int) -> None:
        """Unadvertise a channel; its subscriptions end."""
        with self._lock:
            if self._channels.pop(channel_id, None) is None:
                return
            frame = json.dumps({"op": "unadvertise", "channelIds": [channel_id]})
            for c in self._clients:
                c.subs = {s: ch for s, ch in c.subs.items() if ch != channel_id}
                c.put(frame)

    def log(self, channel_id: int, data: bytes, log_time_ns: int) -> None:
        """Send one message to every client subscribed to the channel."""
        with self._lock:
            for c in self._clients:
                for sub, ch in c.subs.items():
                    if ch == channel_id:
                        c.put(_HEADER.pack(OP_MESSAGE_DATA, sub, log_time_ns) + data)

    # -- one connection ----------------------------------------------------------------
    def _handle(self, conn: ServerConnection) -> None:
        client = _Client(conn)
        info = {
            "op": "serverInfo",
            "name": self.name,
            "capabilities": [],
            "supportedEncodings": [],
            "metadata": {},
        }
        with self._lock:
            client.put(json.dumps(info))
            if self._channels:
                chans = [ch.as_dict() for ch in self._channels.values()]
                client.put(json.dumps({"op": "advertise", "channels": chans}))
            self._clients.append(client)
        sender = threading.Thread(target=self._send_loop, args=(client,), daemon=True)
        sender.start()
        try:
            for raw in conn:
                if isinstance(raw, str):
                    self._on_request(client, raw)
        except Exception as exc:  # a broken connection ends only this client
            log.debug("client %s: %s", conn.remote_address, exc)
        finally:
            with self._lock:
                if client in self._clients:
                    self._clients.remove(client)
                self.dropped += client.dropped
            client.put(None)
            sender.join(timeout=5)

    def _send_loop(self, client: _Client) -> None:
        while True:
            frame = client.out.get()
            if frame is None:
                return
            try:
                client.conn.send(frame)
            except Exception:  # closed: the handler cleans up
                return

    def _status(self, client: _Client, message: str) -> None:
        client.put(json.dumps({"op": "status", "level": 1, "message": message}))

    def _on_request(self, client: _Client, raw: str) -> None:
        try:
            req = json.loads(raw)
            op = req["op"]
        except (ValueError, KeyError, TypeError):
            self._status(client, "not a JSON request with an 'op'")
            return
        with self._lock:
            if op == "subscribe":
                for s in req.get("subscriptions", []):
                    try:
                        sid, cid = int(s["id"]), int(s["channelId"])
                    except (KeyError, TypeError, ValueError):
                        continue
                    if cid in self._channels and sid not in client.subs:
                        client.subs[sid] = cid
                    else:
                        self._status(client, f"subscription {sid}: refused (channel {cid})")
            elif op == "unsubscribe":
                for sid in req.get("subscriptionIds", []):
                    client.subs.pop(sid, None)
            else:
                self._status(client, f"operation {op!r} not supported")
