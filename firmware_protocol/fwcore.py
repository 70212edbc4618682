"""The C firmware core (``firmware_protocol/firmware/``) on the host, through ctypes.

:func:`load_library` builds ``libtruckfw.so`` with ``make -C firmware_protocol/firmware
host`` when it is missing or older than its sources (under a file lock, so concurrent
processes build it once) and loads it.  ``TRUCKD_FW_LIB`` names a prebuilt library
instead; ``TRUCKD_FW_BUILD_DIR`` another build directory (default
``firmware_protocol/firmware/build``, or the user's cache when that is not writable).

:class:`FirmwareCore` is one firmware instance; its hardware is a Python object
implementing :class:`CoreHal` (the simulated plant, see :mod:`truckd.sim.firmware`),
called back from C.  Units are the HAL's: mV, mA, mm,
ticks, ms.  The clock is :attr:`FirmwareCore.now_ms`, set by the caller.

An exception raised in a HAL callback cannot cross C: it is kept and re-raised when the
core call returns (the callback returns a safe value meanwhile).
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Literal, Protocol, TypeVar

from firmware_protocol.timing import limits, timing

FIRMWARE_DIR = Path(__file__).with_name("firmware")
"""Sources and Makefile of the firmware core."""

LIB_NAME = "libtruckfw.so"
ABI_VERSION = 1

# TRUCK_FW_MSG_* (published messages), in DBC-name form
TX_MESSAGES = ("WHEEL_ENCODERS", "MOTOR_FEEDBACK", "RANGE", "FIRMWARE_HEARTBEAT")
TX_FREEZE = 1
TX_BAD_CHECKSUM = 2
TX_STUCK_COUNTER = 4

RANGE_VALID = 0
RANGE_NO_TARGET = 1
RANGE_SENSOR_FAULT = 2

RX_STATS = (
    "frames_ok",
    "checksum_errors",
    "length_errors",
    "unknown_ids",
    "payload_errors",
    "counter_errors",
    "counter_gaps",
    "timeouts",
    "unexpected",
)
FRAMING_STATS = (
    "frames_ok",
    "crc_errors",
    "cobs_errors",
    "length_errors",
    "resyncs",
    "bytes_discarded",
)
FW_STATS = (
    "commands_applied",
    "cmd_timeouts",
    "frames_sent",
    "frames_dropped",
    "tx_failed",
    "schedule_slips",
)


class FirmwareBuildError(RuntimeError):
    """The shared library could not be built or loaded (the message says why)."""


class CoreHal(Protocol):
    """The hardware of one firmware instance (SI-free: mV, mA, mm, ticks)."""

    def read_encoders(self) -> tuple[int, int, int]:
        """(ticks_left, ticks_right) wrapping u16 and status bits (bit 0/1 fault)."""
        ...

    def read_power(self) -> tuple[int, int, int]:
        """(current mA, battery mV, applied voltage mV)."""
        ...

    def read_range(self) -> tuple[int, int]:
        """(RANGE_* status, distance mm)."""
        ...

    def set_motor(self, voltage_mv: int, enable: bool) -> None:
        """Drive the motor (voltage already within the battery)."""
        ...

    def send_bytes(self, data: bytes) -> bool:
        """Serial link: queue wire bytes; False when not sent."""
        ...

    def send_frame(self, can_id: int, data: bytes) -> bool:
        """CAN link: queue one frame; False when not sent."""
        ...


# -- C types -------------------------------------------------------------------------------
_MILLIS = ctypes.CFUNCTYPE(ctypes.c_uint32, ctypes.c_void_p)
_ENC = ctypes.CFUNCTYPE(
    None,
    ctypes.c_void_p,
    ctypes.POINTER(ctypes.c_uint16),
    ctypes.POINTER(ctypes.c_uint16),
    ctypes.POINTER(ctypes.c_uint8),
)


class _Power(ctypes.Structure):
    _fields_ = (
        ("current_ma", ctypes.c_int32),
        ("vbat_mv", ctypes.c_int32),
        ("u_applied_mv", ctypes.c_int32),
    )


_POWER = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.POINTER(_Power))
_RANGE = ctypes.CFUNCTYPE(ctypes.c_uint8, ctypes.c_void_p, ctypes.POINTER(ctypes.c_int32))
_MOTOR = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_int32, ctypes.c_uint8)
_SENDB = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t)
_SENDF = ctypes.CFUNCTYPE(
    ctypes.c_int, ctypes.c_void_p, ctypes.c_uint16, ctypes.c_void_p, ctypes.c_uint8
)


class _Hal(ctypes.Structure):
    _fields_ = (
        ("ctx", ctypes.c_void_p),
        ("millis", _MILLIS),
        ("read_encoders", _ENC),
        ("read_power", _POWER),
        ("read_range", _RANGE),
        ("set_motor", _MOTOR),
        ("send_bytes", _SENDB),
        ("send_frame", _SENDF),
    )


class _Config(ctypes.Structure):
    _fields_ = (
        ("link", ctypes.c_uint8),
        ("timeout_periods", ctypes.c_uint8),
        ("max_wrong_counters", ctypes.c_uint8),
        ("cmd_timeout_ms", ctypes.c_uint16),
        ("undervoltage_mv", ctypes.c_int32),
        ("range_min_mm", ctypes.c_int32),
        ("range_max_mm", ctypes.c_int32),
    )


class _Clock(ctypes.Structure):
    _fields_ = (("now_ms", ctypes.c_uint32),)


_N_STATS = len(RX_STATS) + len(FRAMING_STATS) + len(FW_STATS)
_Stats = ctypes.c_uint32 * _N_STATS


# -- building and loading --------------------------------------------------------------------
def _sources() -> list[Path]:
    d = FIRMWARE_DIR
    return [
        d / "Makefile",
        d / "truck_fw.c",
        d / "truck_fw.h",
        d / "truck_hal.h",
        d / "host" / "truck_fw_host.c",
        d.parent / "c" / "truck.c",
        d.parent / "c" / "truck.h",
        d.parent / "c" / "truck_framing.c",
        d.parent / "c" / "truck_framing.h",
        d.parent / "c" / "truck_timing.h",
    ]


def _build_dir() -> Path:
    override = os.environ.get("TRUCKD_FW_BUILD_DIR")
    if override:
        return Path(override)
    local = FIRMWARE_DIR / "build"
    if os.access(FIRMWARE_DIR, os.W_OK):
        return local
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    cached = cache_home / "truckd" / "firmware"
    base = cached
    while not base.exists() and base != base.parent:
        base = base.parent
    if os.access(base, os.W_OK | os.X_OK):
        return cached
    # A service user without a writable home: a directory of this user's in /tmp.
    return _tmp_build_dir()


def _tmp_build_dir() -> Path:
    return Path(tempfile.gettempdir()) / f"truckd-{os.getuid()}" / "firmware"


def _own_dir_only(build: Path) -> None:
    """The fallback build directory under the shared temporary directory and its parent
    must be this user's and writable by no one else: a library loaded from a directory
    another user made could be theirs.  (An explicit ``TRUCKD_FW_BUILD_DIR`` is the
    user's choice and not checked.)"""
    for d in (build.parent, build):
        st = d.stat()
        if st.st_uid != os.getuid() or st.st_mode & 0o022:
            raise FirmwareBuildError(
                f"{d} belongs to another user or others may write it: not building the "
                "C firmware core there; set TRUCKD_FW_BUILD_DIR to a directory of yours"
            )


def _stale(lib: Path) -> bool:
    if not lib.exists():
        return True
    built = lib.stat().st_mtime
    return any(src.stat().st_mtime > built for src in _sources() if src.exists())


def build_library(force: bool = False) -> Path:
    """Build the host library when missing or stale; its path.  FirmwareBuildError."""
    build = _build_dir()
    lib = build / LIB_NAME
    if not force and not _stale(lib):
        return lib
    if shutil.which("make") is None or shutil.which(os.environ.get("CC", "cc")) is None:
        raise FirmwareBuildError(
            f"the C firmware core ({FIRMWARE_DIR}) must be built but make or a C compiler "
            "is missing: install them (Debian: apt-get install -y make gcc) or set "
            "TRUCKD_FW_LIB to a prebuilt libtruckfw.so"
        )
    try:
        if build == _tmp_build_dir():
            for d in (build.parent, build):  # 0o700 whatever the umask (mkdir's parents)
                if not d.exists():
                    d.mkdir(mode=0o700)
                    d.chmod(0o700)
            _own_dir_only(build)
        else:
            build.mkdir(parents=True, exist_ok=True)
        lock = open(build / ".lock", "w")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise FirmwareBuildError(
            f"cannot build the C firmware core in {build}: {exc.strerror}; set "
            "TRUCKD_FW_BUILD_DIR to a writable directory"
        ) from None
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one build at a time, across processes
        if force or _stale(lib):
            cmd = ["make", "-s", "-C", str(FIRMWARE_DIR), f"BUILD={build}", "host"]
            if force:
                cmd.insert(1, "-B")
            res = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if res.returncode != 0:
                raise FirmwareBuildError(
                    f"building the C firmware core failed ({' '.join(cmd)}):\n"
                    f"{res.stdout}{res.stderr}"
                )
    return lib


@cache
def load_library() -> ctypes.CDLL:
    """The loaded host library (built first when needed), with its ABI checked."""
    override = os.environ.get("TRUCKD_FW_LIB")
    path = Path(override) if override else build_library()
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as exc:
        raise FirmwareBuildError(f"cannot load the C firmware core {path}: {exc}") from None
    _declare(lib)
    if lib.truck_fw_abi_version() != ABI_VERSION:
        raise FirmwareBuildError(f"{path}: ABI version mismatch; rebuild it")
    sizes = {
        "truck_fw_stats_size": ctypes.sizeof(_Stats),
        "truck_fw_config_size": ctypes.sizeof(_Config),
        "truck_hal_size": ctypes.sizeof(_Hal),
    }
    for fn, want in sizes.items():
        got = getattr(lib, fn)()
        if got != want:
            raise FirmwareBuildError(f"{path}: {fn}() = {got}, the binding expects {want}")
    return lib


def _declare(lib: ctypes.CDLL) -> None:
    vp, u8, u16, u32, i32 = (
        ctypes.c_void_p,
        ctypes.c_uint8,
        ctypes.c_uint16,
        ctypes.c_uint32,
        ctypes.c_int32,
    )
    sigs: dict[str, tuple[Any, list[Any]]] = {
        "truck_fw_abi_version": (ctypes.c_uint, []),
        "truck_fw_size": (ctypes.c_size_t, []),
        "truck_fw_stats_size": (ctypes.c_size_t, []),
        "truck_fw_config_size": (ctypes.c_size_t, []),
        "truck_hal_size": (ctypes.c_size_t, []),
        "truck_fw_default_config": (None, [vp]),
        "truck_fw_init": (None, [vp, vp, vp]),
        "truck_fw_rx_bytes": (None, [vp, ctypes.c_char_p, ctypes.c_size_t]),
        "truck_fw_rx_frame": (None, [vp, u16, ctypes.c_char_p, u8]),
        "truck_fw_link_reset": (None, [vp]),
        "truck_fw_poll": (None, [vp]),
        "truck_fw_next_event": (u32, [vp]),
        "truck_fw_state": (u8, [vp]),
        "truck_fw_fault_bits": (u16, [vp]),
        "truck_fw_cmd_errors": (u8, [vp]),
        "truck_fw_voltage_mv": (i32, [vp]),
        "truck_fw_enabled": (u8, [vp]),
        "truck_fw_last_command": (
            ctypes.c_int,
            [vp, ctypes.POINTER(ctypes.c_int16), ctypes.POINTER(u8)],
        ),
        "truck_fw_get_stats": (None, [vp, vp]),
        "truck_fw_rx_fresh": (ctypes.c_int, [vp, ctypes.c_uint]),
        "truck_fw_set_tx_fault": (ctypes.c_int, [vp, ctypes.c_uint, u8]),
        "truck_fw_set_drop": (ctypes.c_int, [vp, ctypes.c_uint, i32]),
        "truck_fw_set_silent": (None, [vp, u8]),
        "truck_fw_clear_faults": (None, [vp]),
    }
    for name, (res, args) in sigs.items():
        f = getattr(lib, name)
        f.restype = res
        f.argtypes = args


# -- one firmware instance -------------------------------------------------------------------
@dataclass(frozen=True)
class CoreConfig:
    """struct truck_fw_config (see truck_fw.h)."""

    link: Literal["serial", "can"] = "serial"
    cmd_timeout_ms: int = round(timing().cmd_timeout * 1000.0)
    timeout_periods: int = timing().freshness_periods
    max_wrong_counters: int = timing().counter_max_wrong
    undervoltage_mv: int = round(limits().undervoltage * 1000.0)
    range_min_mm: int = round(limits().range_min * 1000.0)
    range_max_mm: int = round(limits().range_max * 1000.0)


_R = TypeVar("_R")


class FirmwareCore:
    """One C firmware instance driving ``hal`` (see module docstring)."""

    def __init__(self, hal: CoreHal, config: CoreConfig | None = None, now_ms: int = 0) -> None:
        self._lib = lib = load_library()
        cfg = config or CoreConfig()
        if not 1 <= cfg.cmd_timeout_ms <= 0xFFFF:
            raise ValueError(f"cmd_timeout_ms must be 1..65535, got {cfg.cmd_timeout_ms}")
        self.config = cfg
        self.hal = hal
        self._error: BaseException | None = None
        self._mem = ctypes.create_string_buffer(lib.truck_fw_size())
        self._fw = ctypes.addressof(self._mem)
        self._clock = _Clock(now_ms & 0xFFFFFFFF)
        self._c_cfg = _Config(
            1 if cfg.link == "can" else 0,
            cfg.timeout_periods,
            cfg.max_wrong_counters,
            cfg.cmd_timeout_ms,
            cfg.undervoltage_mv,
            cfg.range_min_mm,
            cfg.range_max_mm,
        )
        # the callbacks must live as long as the core: kept on self
        self._c_hal = _Hal(
            ctypes.addressof(self._clock),
            ctypes.cast(lib.truck_host_millis, _MILLIS),
            _ENC(self._guard(self._encoders, None)),
            _POWER(self._guard(self._power, None)),
            _RANGE(self._guard(self._range, RANGE_SENSOR_FAULT)),
            _MOTOR(self._guard(self._motor, None)),
            _SENDB(self._guard(self._send_bytes, -1)),
            _SENDF(self._guard(self._send_frame, -1)),
        )
        self._call(lib.truck_fw_init, ctypes.byref(self._c_cfg), ctypes.byref(self._c_hal))

    # -- callbacks (C -> Python) -------------------------------------------------------
    def _guard(self, fn: Callable[..., _R], fallback: _R) -> Callable[..., _R]:
        def wrapped(*args: Any) -> _R:
            try:
                return fn(*args)
            except BaseException as exc:  # re-raised by _call after C returns
                if self._error is None:
                    self._error = exc
                return fallback

        return wrapped

    def _encoders(self, ctx: Any, left: Any, right: Any, status: Any) -> None:
        tl, tr, st = self.hal.read_encoders()
        left[0], right[0], status[0] = tl & 0xFFFF, tr & 0xFFFF, st & 0xFF

    def _power(self, ctx: Any, out: Any) -> None:
        i, vb, ua = self.hal.read_power()
        p = out[0]
        p.current_ma, p.vbat_mv, p.u_applied_mv = _i32(i), _i32(vb), _i32(ua)

    def _range(self, ctx: Any, mm: Any) -> int:
        status, dist = self.hal.read_range()
        mm[0] = _i32(dist)
        return status & 0xFF

    def _motor(self, ctx: Any, mv: int, enable: int) -> None:
        self.hal.set_motor(mv, bool(enable))

    def _send_bytes(self, ctx: Any, data: int, n: int) -> int:
        return 0 if self.hal.send_bytes(ctypes.string_at(data, n)) else -1

    def _send_frame(self, ctx: Any, can_id: int, data: int, n: int) -> int:
        return 0 if self.hal.send_frame(can_id, ctypes.string_at(data, n)) else -1

    def _call(self, fn: Callable[..., _R], *args: Any) -> _R:
        res = fn(self._fw, *args)
        if self._error is not None:
            err, self._error = self._error, None
            raise err
        return res

    # -- API -----------------------------------------------------------------------------
    @property
    def now_ms(self) -> int:
        """The clock the core reads (ms, wraps at 2^32)."""
        return int(self._clock.now_ms)

    @now_ms.setter
    def now_ms(self, value: int) -> None:
        self._clock.now_ms = value & 0xFFFFFFFF

    def rx_bytes(self, data: bytes) -> None:
        """Received serial bytes."""
        if data:
            self._call(self._lib.truck_fw_rx_bytes, data, len(data))

    def rx_frame(self, can_id: int, data: bytes) -> None:
        """One received CAN frame (a frame longer than 255 bytes counts as a length error)."""
        self._call(self._lib.truck_fw_rx_frame, can_id & 0xFFFF, data, min(len(data), 255))

    def link_reset(self) -> None:
        """Forget a partial serial frame."""
        self._lib.truck_fw_link_reset(self._fw)

    def poll(self) -> None:
        """Command timeout and every message due at :attr:`now_ms`."""
        self._call(self._lib.truck_fw_poll)

    def next_event(self) -> int:
        """Clock (ms) of the next thing :meth:`poll` will do."""
        return int(self._lib.truck_fw_next_event(self._fw))

    @property
    def state(self) -> int:
        """FIRMWARE_HEARTBEAT.STATE now."""
        return int(self._lib.truck_fw_state(self._fw))

    def fault_bits(self) -> int:
        """Fault bits the next heartbeat reports."""
        return int(self._call(self._lib.truck_fw_fault_bits))

    @property
    def cmd_errors(self) -> int:
        """Rejected commands, mod 256."""
        return int(self._lib.truck_fw_cmd_errors(self._fw))

    @property
    def voltage_mv(self) -> int:
        """Voltage commanded to the driver now."""
        return int(self._lib.truck_fw_voltage_mv(self._fw))

    @property
    def enabled(self) -> bool:
        """Driver enabled now."""
        return bool(self._lib.truck_fw_enabled(self._fw))

    def last_command(self) -> tuple[int, bool] | None:
        """The last valid MOTOR_CMD as received: (voltage mV, enable), None before any."""
        mv, en = ctypes.c_int16(), ctypes.c_uint8()
        if not self._lib.truck_fw_last_command(self._fw, ctypes.byref(mv), ctypes.byref(en)):
            return None
        return int(mv.value), bool(en.value)

    def rx_fresh(self, name: Literal["MOTOR_CMD", "COMPANION_HEARTBEAT"]) -> bool:
        """True when ``name`` arrived within its freshness timeout."""
        idx = 0 if name == "MOTOR_CMD" else 1
        return bool(self._lib.truck_fw_rx_fresh(self._fw, idx))

    def stats(self) -> dict[str, dict[str, int]]:
        """``{"rx": RxStats names, "framing": FramingStats names, "fw": ...}``."""
        raw = _Stats()
        self._lib.truck_fw_get_stats(self._fw, ctypes.byref(raw))
        vals = list(raw)
        a, b = len(RX_STATS), len(RX_STATS) + len(FRAMING_STATS)
        return {
            "rx": dict(zip(RX_STATS, vals[:a], strict=True)),
            "framing": dict(zip(FRAMING_STATS, vals[a:b], strict=True)),
            "fw": dict(zip(FW_STATS, vals[b:], strict=True)),
        }

    # -- test hooks (fault injection) --------------------------------------------------------
    def set_tx_fault(self, message: str, bits: int) -> None:
        """TX_* bits on a published message (replaces its previous bits)."""
        self._lib.truck_fw_set_tx_fault(self._fw, TX_MESSAGES.index(message), bits)

    def set_drop(self, message: str, count: int) -> None:
        """Drop the next ``count`` frames of ``message`` (-1 = until set to 0)."""
        if self._lib.truck_fw_set_drop(self._fw, TX_MESSAGES.index(message), count) != 0:
            raise ValueError(f"drop count must be >= -1, got {count}")

    def set_silent(self, on: bool) -> None:
        """Send nothing (still receives and drives)."""
        self._lib.truck_fw_set_silent(self._fw, int(on))

    def clear_faults(self) -> None:
        """Every hook off."""
        self._lib.truck_fw_clear_faults(self._fw)


def _i32(v: int) -> int:
    return max(-(2**31), min(2**31 - 1, int(v)))
