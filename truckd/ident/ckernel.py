"""The C free-run kernel (truckd/ident/kernel/fastrun.c) through ctypes, when built.

``make firmware`` (and ``make setup-dev firmware``) builds it next to its source; without
it :func:`truckd.ident.freerun.run` runs its Python loop (the reference: same results,
about fifty times slower).  Loading the library is the only thing this module does
besides computing.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

LIBRARY = Path(__file__).resolve().parent / "kernel" / "build" / "libtruckd_fastrun.so"
"""Where ``make firmware`` puts the kernel."""

ABI = 5
"""The kernel version this module calls (``TRUCKD_FASTRUN_ABI`` in ``fastrun.c``): a
library built from another version (or before versions) is refused, the Python loop runs."""

_state: dict[str, ctypes.CDLL | None] = {}


def library() -> ctypes.CDLL | None:
    """The loaded kernel, or None when it is not built (or cannot be loaded)."""
    if "lib" in _state:
        return _state["lib"]
    lib: ctypes.CDLL | None = None
    if LIBRARY.is_file():
        try:
            lib = ctypes.CDLL(str(LIBRARY))
        except OSError:
            lib = None
    if lib is not None and not _current(lib):
        lib = None
    if lib is not None:
        dp = ctypes.c_void_p  # double *, passed as an address
        ip = ctypes.c_void_p  # int64_t *
        d = ctypes.c_double
        i = ctypes.c_int64
        fn = lib.truckd_fastrun
        fn.restype = ctypes.c_int
        fn.argtypes = [
            dp, dp, d, d, d, d, d, d, dp, d, dp, ip, ip, i, i, d, d, dp, dp, dp, dp, dp, dp,
            dp, dp, dp, dp, dp, dp, dp, i, dp, dp, ip, ip, ip, dp, dp, dp, dp,
        ]  # fmt: skip
        sm = lib.truckd_shift_merge
        sm.restype = ctypes.c_int64
        sm.argtypes = [dp, i, dp, i, d, i, i, ip, d, ip, ip, dp, dp, dp, ip, ip]
        fo = lib.truckd_first_order
        fo.restype = ctypes.c_int
        fo.argtypes = [dp, i, i, d, d, dp, dp]
        wr = lib.truckd_winding_rises
        wr.restype = ctypes.c_int
        wr.argtypes = [dp, dp, i, d, d, d, d, d, dp]
    _state["lib"] = lib
    return lib


def _current(lib: ctypes.CDLL) -> bool:
    """Whether ``lib`` is the kernel version :data:`ABI` (a stale build is not)."""
    try:
        version = lib.truckd_fastrun_abi
    except AttributeError:
        return False
    version.restype = ctypes.c_int
    version.argtypes = []
    return int(version()) == ABI


def available() -> bool:
    """Whether the C kernel is built and loads."""
    return library() is not None


def _data(a: NDArray[np.float64] | NDArray[np.int64]) -> int:
    """The address of a contiguous array's data (a writable one through the buffer
    protocol: a third of the time ``a.ctypes.data`` takes)."""
    if a.flags.writeable and a.size:
        # an ndarray exports the buffer protocol (numpy's stubs do not declare it)
        return ctypes.addressof(ctypes.c_char.from_buffer(a))  # type: ignore[arg-type]
    return int(a.ctypes.data)


def _dp(a: NDArray[np.float64] | NDArray[np.int64] | None) -> int | None:
    """The address of a contiguous array's data (None: a NULL pointer)."""
    return None if a is None else _data(a)


ADDRESSES_KEPT = 64
"""Arrays whose data address :func:`_address` keeps, the least recently used dropped first
(a fit passes the same per-command coefficients and timelines run after run while only its
friction or loads change; the arrays of one run do not push those out)."""
_ADDRESSES: dict[int, tuple[NDArray[np.float64] | NDArray[np.int64], int]] = {}


def _address(a: NDArray[np.float64] | NDArray[np.int64]) -> int:
    """:func:`_dp` of a contiguous array, kept for the :data:`ADDRESSES_KEPT` arrays used
    last (the cache holds each array: its identity is not reused, its data does not move)."""
    hit = _ADDRESSES.pop(id(a), None)
    if hit is not None and hit[0] is a:
        _ADDRESSES[id(a)] = hit  # the most recently used last
        return hit[1]
    addr = _data(a)
    _known(a, addr)
    return addr


def _known(a: NDArray[Any], addr: int) -> None:
    """Keep ``addr`` as the data address of ``a``, the least recently used entry dropped
    when full (also for a view into a block whose address is known: the run it goes to
    does not convert it again)."""
    if len(_ADDRESSES) >= ADDRESSES_KEPT:
        del _ADDRESSES[next(iter(_ADDRESSES))]
    _ADDRESSES[id(a)] = (a, addr)


def run(
    a: Array,
    b: Array,
    a_idle: float,
    b_idle: float,
    c: float,
    sigma: float,
    d: float,
    drag: float,
    scale: Array | None,
    lag: float,
    dt: Array,
    cmd: NDArray[np.int64],
    sample_end: NDArray[np.int64],
    n: int,
    w0: float,
    sensor_lag: float,
    terrain: tuple[float, ...] | None = None,
    stribeck: tuple[float, ...] | None = None,
    limit: tuple[float, float] | None = None,
    gap: tuple[tuple[float, ...], Array, Array, Array, Array] | None = None,
    band: Array | None = None,
    heat: HeatArrays | None = None,
) -> tuple[Array, Array, Array] | None:
    """:func:`truckd.ident.freerun.run` in C (None: the kernel is not built).

    ``terrain``: ``(per_newton, ratio, x0, amplitude, wavelength, phase, hill_force,
    hill_start, hill_length)`` of a position-dependent load (see
    :class:`truckd.ident.freerun.Terrain`), None for none.  ``stribeck``: ``(per_nm,
    amplitude, ratio, speed)`` (:class:`truckd.ident.freerun.Stribeck`), None for none.
    ``limit``: ``(a_max, b_mech)`` of a current limit, None for none.  ``gap``: the
    backlash gap as ``(constants, volts, r, state, rotor_out)``
    (:class:`truckd.ident.freerun.GapRun`; ``state`` and ``rotor_out`` are written),
    None for none.  ``band``: two contiguous float64 that receive the run's band of
    breakaway thresholds ``[stuck, moved)`` (per unit inertia, as ``sigma``): without
    ``scale`` and ``stribeck`` every ``sigma`` in it gives this run exactly (None: not
    asked).  ``heat``: a resistance drift stepped beside the speed (:class:`HeatArrays`;
    ``a``, ``b`` and ``scale`` are then written, and must be contiguous float64)."""
    lib = library()
    if lib is None:
        return None
    if heat is not None and not all(_writable(x) for x in (a, b, scale, heat.r, heat.rise)):
        raise ValueError("a heated run writes a, b, scale, r and rise: contiguous float64")
    a = np.ascontiguousarray(a, dtype=np.float64)
    b = np.ascontiguousarray(b, dtype=np.float64)
    sc = None if scale is None else np.ascontiguousarray(scale, dtype=np.float64)
    dt = np.ascontiguousarray(dt, dtype=np.float64)
    cmd = np.ascontiguousarray(cmd, dtype=np.int64)
    se = np.ascontiguousarray(sample_end, dtype=np.int64)
    # The three outputs in one block: one address to convert, the rows at fixed offsets.
    block = np.empty((3, n))
    out, raw, pos = block[0], block[1], block[2]
    at = _data(block)
    row = 8 * n  # bytes per row of float64
    ter = None if terrain is None else np.array(terrain, dtype=np.float64)
    stb = None if stribeck is None else np.array(stribeck, dtype=np.float64)
    lim = None if limit is None else np.array(limit, dtype=np.float64)
    gp = gvolts = gr = gstate = rotor_out = None
    if gap is not None:
        gp = np.array(gap[0], dtype=np.float64)
        gvolts, gr, gstate, rotor_out = gap[1], gap[2], gap[3], gap[4]
        for arr in (gvolts, gr, gstate, rotor_out):
            if arr.dtype != np.float64 or not arr.flags.c_contiguous:
                raise ValueError("the gap's arrays must be contiguous float64")
    f = float
    lib.truckd_fastrun(
        _address(a), _address(b), f(a_idle), f(b_idle), f(c), f(sigma), f(d), f(drag),
        None if sc is None else _address(sc), f(lag), _address(dt), _address(cmd),
        _address(se), len(dt), n, f(w0), f(sensor_lag), at, at + row, at + 2 * row,
        _dp(ter), _dp(stb), _dp(lim), _dp(gp), _dp(gvolts), _dp(gr), _dp(gstate),
        _dp(rotor_out), _dp(band), *(_heat_args(heat) if heat is not None else _NO_HEAT),
    )  # fmt: skip
    return out, raw, pos


@dataclass(frozen=True)
class HeatArrays:
    """A resistance drift stepped beside the speed in one run (``struct heat`` of
    ``fastrun.c``; built by :func:`truckd.ident.fastsim.simulate_voltage`).

    ``constants``: R_m (ohm), tempco (1/K), drift (K/W), tau (s), rise0 (K), L_m (H),
    J_S (kg m^2), K_T, K_v, viscous (N m s/rad), the cold electrical correction, the
    current limit (A, 0: none), v_pre (V), the history commands' extra resistance (ohm).
    Per command: ``volts`` (V), ``sag`` (ohm), ``kk`` (the sample whose rise it sees, -1:
    issued before the log), ``r`` (written: its resistance, ohm).  Per sample: ``at``,
    ``prev`` (the active command and the one before, -1: none), ``since`` (minus the
    time since the active one acted, s), ``h`` (the steps, s), ``rise`` (written, K).
    """

    constants: Array
    volts: Array
    sag: Array
    kk: NDArray[np.int64]
    at: NDArray[np.int64]
    prev: NDArray[np.int64]
    since: Array
    h: Array
    r: Array
    rise: Array


_NO_HEAT = (None, 0, None, None, None, None, None, None, None, None, None)


def _writable(x: Array | None) -> bool:
    return x is not None and x.dtype == np.float64 and x.flags.c_contiguous and x.flags.writeable


def _heat_args(ht: HeatArrays) -> tuple[Any, ...]:
    """``truckd_fastrun``'s heat arguments: the arrays' addresses (each must already be
    contiguous, of its type and size: no temporary copy outlives its address)."""
    m, n = len(ht.volts), len(ht.rise)
    want = [
        (ht.constants, np.float64, 14), (ht.volts, np.float64, m), (ht.sag, np.float64, m),
        (ht.kk, np.int64, m), (ht.at, np.int64, n), (ht.prev, np.int64, n),
        (ht.since, np.float64, n), (ht.h, np.float64, max(n - 1, 0)), (ht.r, np.float64, m),
    ]  # fmt: skip
    for x, kind, size in want:
        if x.dtype != kind or not x.flags.c_contiguous or len(x) != size:
            raise ValueError("heat: contiguous arrays of the commands' and the samples' sizes")
    return (
        _dp(ht.constants), m, _dp(ht.volts), _dp(ht.sag), _dp(ht.kk), _dp(ht.at),
        _dp(ht.prev), _dp(ht.since), _dp(ht.h), _dp(ht.r), _dp(ht.rise),
    )  # fmt: skip


def shift_merge(
    t: Array,
    t_cmd: Array,
    delay: float,
    first: int,
    stop: int,
    order: NDArray[np.int64],
    eps: float,
    cmd: NDArray[np.int64],
    sample_end: NDArray[np.int64],
    a: Array,
    b: Array,
) -> tuple[Array, NDArray[np.int64], NDArray[np.int64]] | None:
    """:func:`truckd.ident.timing.shifted` then :func:`truckd.ident.timing.merged` in C
    for a layout's ``first``, ``stop``, ``order``, ``eps``, ``cmd`` and ``sample_end``:
    the merged timeline's ``(dt, cmd, sample_end)``; None when the layout's order does not
    hold under ``delay`` (s), or the kernel is not built (:func:`available`)."""
    lib = library()
    if lib is None:
        return None
    subs = len(cmd)
    # The three outputs in one block (one address to convert): dt, then cmd and sample_end.
    block = np.empty(3 * subs)
    at = _data(block)
    f = float
    count = lib.truckd_shift_merge(
        _address(t), len(t), _address(t_cmd), len(t_cmd), f(delay), first, stop,
        _address(order), f(eps), _address(cmd), _address(sample_end), _address(a), _address(b),
        at, at + 8 * subs, at + 16 * subs,
    )  # fmt: skip
    if count < 0:
        return None
    ints = block[subs:].view(np.int64)
    out = block[:count], ints[:count], ints[subs : subs + count]
    for k, view in enumerate(out):  # the free run that follows passes them on
        _known(view, at + 8 * subs * k)
    return out


def winding_rises(
    h: Array, sq: Array, rise0: float, r_m: float, tempco: float, drift: float, tau: float
) -> Array | None:
    """:func:`truckd.ident.fastsim.winding_rises` in C (None: the kernel is not built):
    the rise (K) at each sample from ``rise0``, ``sq`` the squared currents (A^2), ``h``
    the time steps (s, one fewer); ``r_m`` (ohm), ``tempco`` (1/K), ``drift`` (K/W),
    ``tau`` (s) as :func:`truckd.model.effects.winding_rise_step`."""
    lib = library()
    if lib is None:
        return None
    h = np.ascontiguousarray(h, dtype=np.float64)
    sq = np.ascontiguousarray(sq, dtype=np.float64)
    out = np.empty(len(sq))
    lib.truckd_winding_rises(
        _dp(h), _dp(sq), len(sq), float(rise0), float(r_m), float(tempco), float(drift),
        float(tau), _dp(out),
    )  # fmt: skip
    return out


def first_order(x: Array, b1: float, a1: float) -> Array | None:
    """``scipy.signal.lfilter([0, b1], [1, a1], x, axis=0)`` of a 2-D ``x`` in C, the
    same numbers (scipy's direct form II transposed, from rest); None when the kernel is
    not built."""
    lib = library()
    if lib is None:
        return None
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"x must be 2-D, got shape {x.shape}")
    rows, cols = x.shape
    y = np.empty((rows, cols))
    z = np.empty(cols)
    lib.truckd_first_order(_dp(x), rows, cols, float(b1), float(a1), _dp(z), _dp(y))
    return y
