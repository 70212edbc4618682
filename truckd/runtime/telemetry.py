"""Zenoh telemetry (reference section 5) that never blocks the control loop.

The loop hands dicts, or state messages still to be built
(:class:`~truckd.runtime.deferred.Deferred`), to :meth:`Telemetry.publish_state` /
:meth:`publish_health`, which only append to a bounded deque (the oldest message is dropped
and counted when it is full) and set an event.  A worker thread builds what is deferred,
encodes JSON and puts to Zenoh with congestion control ``DROP``, so a slow or absent
subscriber costs the loop nothing.

Keys, for ``vehicle_id`` V: ``truckd/V/state``, ``truckd/V/health``, liveliness token
``truckd/V/alive``, queryable ``truckd/V/params``.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from truckd.config.runtime import TelemetryConfig
from truckd.errors import InputError, TruckdError
from truckd.inputs import open_regular
from truckd.runtime.deferred import MessageSource, resolve

log = logging.getLogger("truckd.telemetry")

_encode = json.JSONEncoder(allow_nan=True, check_circular=False, separators=(",", ":")).encode
"""One encoder for every message (``json.dumps`` builds one per call with these options);
compact separators, the messages are plain dicts without cycles."""

Extra = Callable[[], dict[str, Any]] | None
"""Computed on the publisher thread and merged into the message (costly statistics)."""


def default_zenoh_config_path() -> Path:
    """The shipped Zenoh configuration (``config/zenoh.json5`` in the source tree)."""
    return Path(__file__).resolve().parent.parent / "defaults" / "zenoh.json5"


def _port_out_of_range(endpoint: str) -> bool:
    """An IP endpoint (``tcp/HOST:PORT``, ``udp``, ``tls``, ``quic``) whose port is above
    65535 (Zenoh accepts it and never connects)."""
    head = endpoint.split("#", 1)[0].split("?", 1)[0]
    if head.split("/", 1)[0] not in ("tcp", "udp", "tls", "quic", "ws"):
        return False
    _, sep, port = head.rpartition(":")
    return bool(sep) and port.isdigit() and int(port) > 65535


def _set_endpoints(conf: zenoh.Config, key: str, endpoints: Sequence[str], name: str) -> None:
    """``conf[key] = endpoints``; InputError naming ``name`` and the bad endpoint."""
    for e in endpoints:
        if _port_out_of_range(e):
            raise InputError(f"{name} {e!r}: port above 65535; expected a port in 1..65535")
    try:
        conf.insert_json5(key, json.dumps(list(endpoints)))
        return
    except Exception:  # zenoh's ZError: find the endpoint it refused
        pass
    bad = list(endpoints)
    for e in endpoints:
        try:
            conf.insert_json5(key, json.dumps([e]))
        except Exception:
            bad = [e]
            break
    raise InputError(
        f"{name} {', '.join(map(repr, bad))}: not a Zenoh endpoint; expected "
        "<protocol>/<address>, e.g. tcp/127.0.0.1:7447"
    )


def zenoh_config(
    path: str | Path = "",
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    *,
    names: tuple[str, str] = ("listen", "connect"),
) -> zenoh.Config:
    """Load a Zenoh JSON5 file (the shipped one when ``path`` is empty) and override its
    listen/connect endpoints when given (``None`` keeps the file's; ``[]`` clears).

    A bad file or endpoint raises InputError; ``names`` are what the error calls the
    listen and connect settings (a config key, a command-line option)."""
    p = Path(path) if path else default_zenoh_config_path()
    os.close(open_regular(p, "Zenoh configuration file (JSON5)", 1024 * 1024))  # not /dev/zero
    try:
        conf = zenoh.Config.from_file(str(p))
    except Exception as exc:  # zenoh raises its own ZError for bad files
        raise InputError(f"{p}: not a valid Zenoh configuration: {exc}") from None
    if listen is not None:
        _set_endpoints(conf, "listen/endpoints", listen, names[0])
    if connect is not None:
        _set_endpoints(conf, "connect/endpoints", connect, names[1])
    return conf


def _limit_ingress(conf: zenoh.Config, limits: dict[str, float]) -> None:
    """Add an ingress downsampling rule per key (kept with the file's own rules)."""
    try:
        rules = json.loads(conf.get_json("downsampling"))
    except Exception:  # not set in the file
        rules = None
    rules = rules if isinstance(rules, list) else []
    rules.append(
        {
            "id": "truckd_ingress",
            "messages": ["put", "delete"],
            "flows": ["ingress"],
            "rules": [{"key_expr": k, "freq": float(hz)} for k, hz in limits.items()],
        }
    )
    conf.insert_json5("downsampling", json.dumps(rules))


def open_session(conf: zenoh.Config, what: str) -> zenoh.Session:
    """Open a Zenoh session; a failure (e.g. the port is taken) becomes a TruckdError."""
    try:
        return zenoh.open(conf)
    except Exception as exc:
        raise TruckdError(f"cannot open Zenoh session for {what}: {exc}") from None


def keys(vehicle_id: str) -> dict[str, str]:
    """The Zenoh key expressions of one vehicle."""
    base = f"truckd/{vehicle_id}"
    return {k: f"{base}/{k}" for k in ("state", "health", "alive", "params", "plan")}


class Telemetry:
    """Publishes state and health, holds the liveliness token, answers params queries."""

    def __init__(
        self,
        vehicle_id: str,
        cfg: TelemetryConfig,
        params: Callable[[], dict[str, Any]],
    ) -> None:
        self.cfg = cfg
        self.keys = keys(vehicle_id)
        self._params = params
        self._q: deque[tuple[str, MessageSource, Extra]] = deque(maxlen=cfg.queue_size)
        self._event = threading.Event()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._session: zenoh.Session | None = None
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._token: zenoh.LivelinessToken | None = None
        self._queryable: zenoh.Queryable[None] | None = None
        self._subs: list[zenoh.Subscriber[None]] = []
        self._ingress: dict[str, float] = {}  # key -> most samples per second let in
        self.dropped = 0  # messages dropped because the queue was full
        self.sent = 0
        self.errors = 0  # puts that raised
        self.queries = 0

    def start(self) -> None:
        """Open the session and declare everything (blocking; call before the loop)."""
        c = self.cfg
        conf = zenoh_config(
            c.zenoh_config,
            c.listen or None,
            c.connect or None,
            names=("runtime.telemetry.listen", "runtime.telemetry.connect"),
        )
        if self._ingress:
            _limit_ingress(conf, self._ingress)
        self._session = s = open_session(conf, self.keys["state"])
        for k in ("state", "health", "plan"):
            self._pubs[k] = s.declare_publisher(
                self.keys[k],
                encoding=zenoh.Encoding.APPLICATION_JSON,
                congestion_control=zenoh.CongestionControl.DROP,
            )
        self._queryable = s.declare_queryable(self.keys["params"], self._on_query)
        self._token = s.liveliness().declare_token(self.keys["alive"])
        self._thread = threading.Thread(target=self._run, name="truckd-telemetry", daemon=True)
        self._thread.start()
        log.info("zenoh telemetry on %s (listen %s)", self.keys["state"], conf.get_json("listen"))

    def limit_ingress(self, key: str, hz: float) -> None:
        """Let at most ``hz`` samples per second on ``key`` into this session (Zenoh's
        ingress downsampling: the rest are dropped in Zenoh, before any Python callback
        runs).  Only before :meth:`start`."""
        if self._session is not None:
            raise RuntimeError("Telemetry.limit_ingress after start")
        self._ingress[key] = hz

    def subscribe(self, suffix: str, callback: Callable[[bytes], None]) -> None:
        """Call ``callback(payload)`` for each sample on ``truckd/<vehicle_id>/<suffix>``
        (on Zenoh's thread).  Only after :meth:`start`."""
        self.subscribe_key(self.keys["state"].rsplit("/", 1)[0] + "/" + suffix, callback)

    def subscribe_key(self, key: str, callback: Callable[[bytes], None]) -> None:
        """Call ``callback(payload)`` for each sample on ``key`` (on Zenoh's thread), e.g.
        the predecessor's plan in a platoon.  Only after :meth:`start`."""
        if self._session is None:
            raise RuntimeError("Telemetry.subscribe before start")

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(sample.payload.to_bytes())
            except Exception as exc:  # never kill zenoh's callback thread
                log.warning("%s handler failed: %s", key, exc)

        self._subs.append(self._session.declare_subscriber(key, on_sample))

    def subscribe_raw(self, key: str, callback: Callable[[zenoh.ZBytes], None]) -> None:
        """Like :meth:`subscribe_key`, passing the payload uncopied (``to_bytes()`` when
        needed): the callback's work does not grow with the payload's size."""
        if self._session is None:
            raise RuntimeError("Telemetry.subscribe before start")

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(sample.payload)
            except Exception as exc:  # never kill zenoh's callback thread
                log.warning("%s handler failed: %s", key, exc)

        self._subs.append(self._session.declare_subscriber(key, on_sample))

    def subscribe_keyed(self, key: str, callback: Callable[[str, zenoh.ZBytes], None]) -> None:
        """Like :meth:`subscribe_raw` on a key expression (e.g. ``truckd/*/plan``),
        passing the sample's key as well: ``callback(key, payload)``."""
        if self._session is None:
            raise RuntimeError("Telemetry.subscribe before start")

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(str(sample.key_expr), sample.payload)
            except Exception as exc:  # never kill zenoh's callback thread
                log.warning("%s handler failed: %s", key, exc)

        self._subs.append(self._session.declare_subscriber(key, on_sample))

    def declare(self, suffix: str) -> None:
        """One more publisher, on ``truckd/<vehicle_id>/<suffix>`` (JSON; e.g.
        ``characterize``): after :meth:`start`, before the loop (declaring blocks)."""
        if self._session is None:
            raise RuntimeError("Telemetry.declare before start")
        key = self.keys["state"].rsplit("/", 1)[0] + "/" + suffix
        self.keys[suffix] = key
        self._pubs[suffix] = self._session.declare_publisher(
            key,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.DROP,
        )

    def publish(self, suffix: str, msg: dict[str, Any]) -> None:
        """Queue one message on a key :meth:`declare` declared (never blocks)."""
        self._enqueue(suffix, msg)

    def _on_query(self, query: zenoh.Query) -> None:
        self.queries += 1
        try:
            # on this truck's own key: a query on ``truckd/*/params`` tells the replies
            # apart by their keys
            query.reply(self.keys["params"], json.dumps(self._params()))
        except Exception as exc:  # a bad query must not kill zenoh's callback thread
            log.warning("params query failed: %s", exc)

    def _enqueue(self, kind: str, msg: MessageSource, extra: Extra = None) -> None:
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        self._q.append((kind, msg, extra))
        # One wake-up per batch: an Event.set is a Condition round trip (and a futex wake
        # of the publisher thread).  Already set: the publisher clears it before it drains
        # the queue, so what was just appended is drained in that pass.
        if not self._event.is_set():
            self._event.set()

    def publish_state(self, msg: MessageSource) -> None:
        """Queue one state message, or a :class:`~truckd.runtime.deferred.Deferred` that
        builds it on the publisher thread (never blocks)."""
        self._enqueue("state", msg)

    def publish_plan(self, msg: dict[str, Any]) -> None:
        """Queue this cycle's plan (``truckd/<vehicle_id>/plan``; never blocks)."""
        self._enqueue("plan", msg)

    def publish_health(self, msg: dict[str, Any], extra: Extra = None) -> None:
        """Queue one health message (never blocks); ``extra()`` is merged into it on the
        publisher thread."""
        self._enqueue("health", msg, extra)

    def _run(self) -> None:
        while True:
            self._event.wait(0.2)
            self._event.clear()
            while self._q:
                try:
                    kind, msg, extra = self._q.popleft()
                except IndexError:
                    break
                try:
                    msg = resolve(msg)  # a deferred one is built here, off the control loop
                    if extra is not None:
                        msg = {**msg, **extra()}
                    self._pubs[kind].put(_encode(msg))
                    self.sent += 1
                except Exception as exc:
                    self.errors += 1
                    if self.errors <= 3:
                        log.warning("zenoh put failed: %s", exc)
            if self._stop:
                return

    def close(self, timeout: float = 1.0) -> None:
        """Send what is queued (up to ``timeout``), drop the token, close the session."""
        self._stop = True
        self._event.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        for sub in self._subs:
            sub.undeclare()  # type: ignore[no-untyped-call]
        self._subs.clear()
        if self._token is not None:
            self._token.undeclare()  # type: ignore[no-untyped-call]
            self._token = None
        if self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]
            self._session = None
