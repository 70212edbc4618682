"""``truckd monitor --foxglove``: every reachable vehicle's state, health and plan, live, on
a Foxglove WebSocket server (:mod:`truckd.runtime.foxglove_ws`, our own on the published
protocol, under both subprotocol names ``foxglove.websocket.v1`` and ``foxglove.sdk.v1``;
the ``websockets`` package, optional extra ``[foxglove]``).

A Zenoh peer session that listens nowhere connects to the given endpoints and subscribes
to ``truckd/*/state``, ``truckd/*/health``, ``truckd/*/plan``; the first sample of a
vehicle's kind advertises the channel ``/truckd/<vehicle_id>/<kind>`` (JSON, with the
JSON schema of :mod:`truckd.runtime.msg_schemas`, the same as in the MCAP log), and every
sample is forwarded as it is (re-encoded only when it holds NaN or infinities, which JSON
has not).  A vehicle whose liveliness token goes has its channels closed (unadvertised)
until it is heard again.  The server binds 127.0.0.1 unless told otherwise.  The log time
is the relay's wall clock when the sample arrived (ns since the Unix epoch).

``websockets`` is imported only when the relay starts.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TextIO

import zenoh

from truckd.errors import TruckdError
from truckd.runtime.mcap_log import to_json
from truckd.runtime.monitor import MAX_VEHICLES
from truckd.runtime.msg_schemas import KINDS, MESSAGE_ENCODING, SCHEMA_ENCODING, schema_bytes
from truckd.runtime.msg_schemas import topic as topic_of
from truckd.runtime.stopping import stop_signals, ticks
from truckd.runtime.telemetry import open_session, zenoh_config

if TYPE_CHECKING:
    from truckd.runtime.foxglove_ws import FoxgloveServer

log = logging.getLogger("truckd.foxglove")

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port."""


def _split(key: str) -> tuple[str, str] | None:
    """``truckd/<vid>/<kind>`` -> (vid, kind); None for anything else."""
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "truckd" and parts[1] and parts[2] in KINDS:
        return parts[1], parts[2]
    return None


def clean_payload(payload: bytes) -> bytes | None:
    """The payload as strict JSON (NaN/inf -> null); None when it is not a JSON object
    (checked for every payload: bytes that are not JSON, a list or a number used to pass
    unchanged to a JSON channel when they held no NaN)."""
    try:
        msg = json.loads(payload)
    except (ValueError, RecursionError):  # not JSON, or nested beyond the stack
        return None
    if not isinstance(msg, dict):
        return None
    if b"NaN" not in payload and b"Infinity" not in payload:
        return payload
    return to_json(msg)


@dataclass
class RelayStats:
    """What went through, per topic."""

    messages: dict[str, int] = field(default_factory=dict)
    rejected: int = 0  # payloads that were not JSON objects


class FoxgloveRelay:
    """Zenoh -> Foxglove WebSocket (see module docstring).  ``start()``, ``close()``."""

    def __init__(
        self,
        connect: Sequence[str],
        zenoh_file: str = "",
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.connect = list(connect)
        self.zenoh_file = zenoh_file
        self.host = host
        self.port = port
        self._clock_ns = clock_ns
        self._server: FoxgloveServer | None = None
        self._session: zenoh.Session | None = None
        self._subs: list[Any] = []
        self._channels: dict[tuple[str, str], int] = {}  # (vehicle, kind) -> channel id
        self._lock = threading.Lock()
        self.stats = RelayStats()

    def start(self) -> int:
        """Start the server and the Zenoh subscribers; returns the port bound (raises
        TruckdError when websockets is missing or the port is taken, InputError for a
        bad endpoint)."""
        try:
            import websockets.sync.server  # noqa: F401 - only to fail early and clearly
        except ImportError:
            raise TruckdError(
                "monitor --foxglove needs the websockets package: pip install 'truckd[foxglove]'"
            ) from None
        from truckd.runtime.foxglove_ws import FoxgloveServer

        conf = zenoh_config(
            self.zenoh_file, listen=[], connect=self.connect, names=("", "--connect")
        )
        server = FoxgloveServer(name="truckd", host=self.host, port=self.port)
        try:
            self.port = server.start()
        except OSError as exc:
            raise TruckdError(
                f"cannot start the Foxglove server on {self.host}:{self.port}: "
                f"{exc.strerror or exc}"
            ) from None
        self._server = server
        try:
            self._session = s = open_session(conf, "monitor --foxglove")
        except BaseException:
            server.stop()
            self._server = None
            raise
        for kind in KINDS:
            self._subs.append(s.declare_subscriber(f"truckd/*/{kind}", self._on_sample))
        self._subs.append(
            s.liveliness().declare_subscriber("truckd/*/alive", self._on_alive, history=True)
        )
        return self.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def _channel(self, vid: str, kind: str) -> int | None:
        """The channel id of a vehicle's kind, advertised on first use; None for a vehicle
        beyond :data:`MAX_VEHICLES` (a flood of vehicle ids: channels are bounded)."""
        with self._lock:
            ch = self._channels.get((vid, kind))
            if ch is None:
                vehicles = {v for v, _ in self._channels}
                if (vid not in vehicles and len(vehicles) >= MAX_VEHICLES) or not self._server:
                    return None
                ch = self._server.add_channel(
                    topic_of(vid, kind),
                    MESSAGE_ENCODING,
                    f"truckd.{kind}",
                    schema_bytes(kind),
                    SCHEMA_ENCODING,
                )
                self._channels[(vid, kind)] = ch
                log.info("relaying %s", topic_of(vid, kind))
            return ch

    def on_payload(self, key: str, payload: bytes) -> None:
        """One Zenoh sample (called on Zenoh's threads; public for tests)."""
        vk = _split(key)
        if vk is None:
            return
        data = clean_payload(payload)
        if data is None:
            self.stats.rejected += 1
            return
        ch = self._channel(*vk)
        server = self._server
        if ch is None or server is None:
            self.stats.rejected += 1
            return
        server.log(ch, data, self._clock_ns())
        t = topic_of(*vk)
        self.stats.messages[t] = self.stats.messages.get(t, 0) + 1

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self.on_payload(str(sample.key_expr), sample.payload.to_bytes())
        except Exception as exc:  # never kill zenoh's callback thread
            log.warning("relay failed for %s: %s", sample.key_expr, exc)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if sample.kind != zenoh.SampleKind.DELETE or len(parts) != 3:
            return
        with self._lock:  # the vehicle went: unadvertise its channels
            for kind in KINDS:
                ch = self._channels.pop((parts[1], kind), None)
                if ch is not None and self._server is not None:
                    self._server.remove_channel(ch)

    def close(self) -> None:
        """Undeclare, close the session and the channels, stop the server (idempotent)."""
        for sub in self._subs:
            sub.undeclare()
        self._subs.clear()
        if self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]
            self._session = None
        with self._lock:
            self._channels.clear()
            server, self._server = self._server, None
        if server is not None:
            server.stop()


def run_relay(
    relay: FoxgloveRelay,
    out: TextIO,
    *,
    duration: float | None,
    interval: float,
    clock: Callable[[], float] = time.monotonic,
) -> RelayStats:
    """Start ``relay``, print its address and, every ``interval`` s when it changed, how
    many messages went out per topic; until ``duration`` (None: until SIGTERM, which
    ends it normally, or Ctrl-C, which raises KeyboardInterrupt: :mod:`truckd.runtime.stopping`)."""
    port = relay.start()
    # The stop signals' handlers are installed after the start: the native libraries
    # (Zenoh, the Foxglove server) set up their runtimes there, and with Python's own
    # SIGINT handler beneath them a Ctrl-C was now and then not seen (the relay kept
    # running; about 1 run in 20 beside a busy core).
    with stop_signals():
        try:
            out.write(f"foxglove: serving on ws://{relay.host}:{port} (open it in Foxglove)\n")
            out.flush()
            last = ""
            for _ in ticks(interval, duration, clock):
                line = ", ".join(f"{t} {n}" for t, n in sorted(relay.stats.messages.items()))
                if line and line != last:
                    out.write(f"relayed: {line}\n")
                    out.flush()
                    last = line
        finally:
            relay.close()
    return relay.stats
