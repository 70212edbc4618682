"""The ``runtime:`` section of truck.yaml: loop, backend, real-time, telemetry, recorder,
supervisor.  Every field has a default; the daemon reads nothing else from the file."""

from __future__ import annotations

from dataclasses import dataclass

from truckd.control.supervisor import SupervisorConfig
from truckd.io.backends import BACKEND_NAMES
from truckd.schema import spec


@dataclass(frozen=True)
class TelemetryConfig:
    """Zenoh publishing (reference section 5)."""

    enabled: bool = spec("publish over Zenoh", default=True)
    zenoh_config: str = spec(
        "Zenoh 1.x JSON5 configuration file; empty: the shipped config/zenoh.json5", default=""
    )
    listen: tuple[str, ...] = spec(
        "listen endpoints, overriding the Zenoh file when not empty", default=()
    )
    connect: tuple[str, ...] = spec(
        "connect endpoints, overriding the Zenoh file when not empty", default=()
    )
    state_every: int = spec("publish state every N control cycles", lo=1, hi=100_000, default=1)
    health_period_s: float = spec("health message period", unit="s", lo=0.05, hi=1.0, default=0.5)
    queue_size: int = spec(
        "messages waiting for the publisher thread; the oldest is dropped beyond this",
        lo=4,
        hi=1_000_000,
        default=256,
    )


@dataclass(frozen=True)
class RecorderConfig:
    """The daemon's own log, in the contract CSV format (reference section 3)."""

    enabled: bool = spec("record a log", default=True)
    dir: str = spec("directory for log files (relative: to the working directory)", default="logs")
    max_bytes: int = spec(
        "rotate to a new file beyond this size", unit="B", lo=4096, default=20_000_000
    )
    keep: int = spec("rotated files kept (oldest deleted)", lo=1, hi=1_000_000, default=20)
    flush_period_s: float = spec(
        "flush to disk at least this often (what a crash can lose)",
        unit="s",
        lo=0.0,
        hi=3600.0,
        default=1.0,
    )
    mcap: bool = spec(
        "also write MCAP (state, health, plan channels) beside each CSV, for Foxglove",
        default=True,
    )
    mcap_state_every: int = spec(
        "record the state in MCAP every N control cycles", lo=1, hi=100_000, default=1
    )
    mcap_plan_every: int = spec(
        "record every N-th plan in MCAP (a 40-step plan costs the writer ~40 us to encode)",
        lo=1,
        hi=100_000,
        default=10,
    )
    mcap_compression: str = spec(
        "MCAP chunk compression", choices=("zstd", "lz4", "none"), default="zstd"
    )
    messages: bool = spec(
        "also record every received message (<log>.rx.jsonl beside each CSV, rotated and "
        "deleted with it) so the run can be replayed through the control cycle",
        default=True,
    )


@dataclass(frozen=True)
class RuntimeConfig:
    """How ``truckd run`` runs.  The loop rate is ``control.rate_hz`` (one source of
    truth: the MPC step is its period); the lead-lost action is ``control.on_lead_lost``."""

    backend: str = spec(
        "link backend (device settings in the link: section)",
        choices=BACKEND_NAMES,
        default="sim",
    )
    realtime: bool = spec("try SCHED_FIFO and mlockall (logged when not permitted)", default=True)
    rt_priority: int = spec("SCHED_FIFO priority", lo=1, hi=99, default=50)
    cpu_latency_us: int = spec(
        "with realtime: the CPU wake-up latency to hold while running (Linux PM QoS, "
        "/dev/cpu_dma_latency; 0 keeps the cores out of deep idle states: faster cycles, "
        "more power); -1 leaves the kernel's idle policy alone",
        unit="us",
        lo=-1,
        hi=1_000_000,
        default=0,
    )
    stop_ramp_v_per_s: float = spec(
        "voltage ramp towards 0 V in SAFE_STOP", unit="V/s", lo=0.0, lo_open=True, default=60.0
    )
    stall_limit_s: float = spec(
        "the loop woke this much later than its previous cycle (a stall: SIGSTOP, a frozen "
        "host): logged, published in health, and the control state re-initialised (estimator "
        "restarted, MPC warm start dropped, INIT with the motor off until the sensors are "
        "fresh again) before driving on; at least two control periods",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=60.0,
        default=0.05,
    )
    fault_injection: bool = spec(
        "accept injected faults on truckd/<vehicle_id>/inject (HIL tests only)", default=False
    )
    supervisor: SupervisorConfig = spec("mode thresholds", default_factory=SupervisorConfig)
    telemetry: TelemetryConfig = spec("Zenoh publishing", default_factory=TelemetryConfig)
    recorder: RecorderConfig = spec("CSV log recording", default_factory=RecorderConfig)
