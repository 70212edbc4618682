"""``truckd sim --platoon N --mixed``: each drawn truck's controller on the model its own
identification drive diagnoses.

For each drawn truck (:func:`truckd.sim.platoon_truck.draw_platoon_truck`, its dead time
set) this makes the log a user of that truck would have and the model they would load
with ``--model``:

1. the truck's own identification drive: ``truckd characterize``'s routine on the daemon
   (:func:`truckd.cli.characterize.drive`, the ``sim`` backend in simulated time) with
   the drawn truck as the simulated plant (``plant.vehicle`` and ``plant.effects``: the
   truth, the dead time included) and the configured truck as ``vehicle:``;
2. the diagnosis ``truckd diagnose`` and ``truckd characterize`` run
   (:func:`truckd.ident.api.diagnose_log` from the configured truck, the chirp
   validating), its extended model (:func:`truckd.ident.api.model_of`);
3. the truck's controller on that model (``ControlModel(vehicle, effects)``, as ``--model``
   gives it; its rate weight and input blocks tuned to the diagnosed model,
   :func:`truckd.sim.platoon_truck.on_model`), while its plant stays the drawn truth.

A drive and its diagnosis take some seconds per truck (about 2 s and 6 s on one core).
Identical trucks are diagnosed once per process (the key is the whole identification
configuration: the drawn truck, its sensors, the configured truck and the ``characterize``
section); with ``cache_dir`` the models are also kept on disk, keyed by that
configuration and by a digest of truckd's own source and the numerical libraries'
versions (a change of any of them misses the cache).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from truckd.config.truck import TruckConfig
from truckd.control.qp import ControlModel
from truckd.errors import InputError, TruckdError
from truckd.ident.api import diagnose_log, model_of, require_physical
from truckd.ident.linear import feedforward_of
from truckd.model.params import VehicleParams
from truckd.model.plant_config import PlantVehicle
from truckd.modelfile import ModelFile, read_model, write_model
from truckd.runtime.characterize_plan import EXIT_DONE
from truckd.runtime.ratekeeper import SteppedClock
from truckd.sim.closed_loop import SimSetup
from truckd.sim.platoon_truck import on_model
from truckd.workers import ForkMap

Progress = Callable[[str], None]

DIAGNOSIS_JOBS_MAX = 4
"""Worker processes ``truckd sim --mixed`` drives and diagnoses the drawn trucks on, at
most (and at most the CPUs the process may use)."""

_MEMO: dict[str, ModelFile] = {}
"""Diagnosed models of this process, by :func:`identification_key`."""


def _quiet(_: str) -> None:
    return None


def identification_config(cfg: TruckConfig, truth: SimSetup) -> TruckConfig:
    """``cfg`` with the drawn truck ``truth`` as its simulated plant (every vehicle
    parameter, the effects with the dead time, its sensors and encoder), no real-time
    scheduling, telemetry off and the recorder writing CSV only: what the identification
    drive runs on."""
    p = truth.plant_params
    vehicle = PlantVehicle(**{f.name: getattr(p, f.name) for f in dataclasses.fields(PlantVehicle)})
    rt = cfg.runtime
    runtime = dataclasses.replace(
        rt,
        realtime=False,  # in-process: the sim's own scheduling stays as it is
        telemetry=dataclasses.replace(rt.telemetry, enabled=False),
        recorder=dataclasses.replace(rt.recorder, mcap=False, messages=False),
    )
    return dataclasses.replace(
        cfg,
        plant=dataclasses.replace(truth.plant_config, vehicle=vehicle),
        link=dataclasses.replace(cfg.link, encoder_ticks_per_rev=truth.ticks_per_rev),
        runtime=runtime,
    )


def identification_key(tcfg: TruckConfig) -> str:
    """What determines a diagnosed model in this process: the identification
    configuration (exact: dataclass reprs, floats as they round-trip)."""
    return repr(tcfg)


_DIGEST: list[str] = []


def code_digest() -> str:
    """SHA-256 over truckd's and firmware_protocol's Python and C sources (the fitting
    kernel, the firmware core), whether each compiled library is built, and the versions
    of Python, numpy and scipy: a disk-cached model is reused only by the code that made
    it."""
    if not _DIGEST:
        import numpy
        import scipy

        import firmware_protocol
        import truckd

        versions = f"python {sys.version} numpy {numpy.__version__} scipy {scipy.__version__}"
        h = hashlib.sha256(versions.encode())
        for pkg in (truckd, firmware_protocol):
            root = Path(str(pkg.__file__)).parent
            for f in sorted(root.rglob("*")):
                if f.suffix in (".py", ".c", ".h") and "build" not in f.parts:
                    h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes())
                elif f.suffix == ".so":  # built or not: the C path or the Python loop
                    h.update(str(f.relative_to(root)).encode())
        _DIGEST.append(h.hexdigest())
    return _DIGEST[0]


@contextmanager
def _daemon_quiet() -> Iterator[None]:
    """The identification drive's daemon logs its mode changes; not on the sim's stderr."""
    log = logging.getLogger("truckd.daemon")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


def identify_truck(cfg: TruckConfig, truth: SimSetup) -> ModelFile:
    """The model the drawn truck ``truth``'s own identification drive diagnoses (from
    ``cfg.vehicle``, the configured truck); TruckdError when the drive does not complete
    or the diagnosed model is not physical."""
    from truckd.cli.characterize import drive, experiment_log, split_validation

    tcfg = identification_config(cfg, truth)
    with tempfile.TemporaryDirectory(prefix="truckd-ident-") as tmp, _daemon_quiet():
        result, d = drive(tcfg, "sim", Path(tmp) / "drive", _quiet, None, SteppedClock())
        files = list(d.recorder.files) if d.recorder is not None else []
        log = experiment_log(files, result.experiments, result.stop_t)
    if result.code != EXIT_DONE or log is None:
        raise TruckdError(
            f"the identification drive of a drawn truck did not complete (exit {result.code}"
            f"{', ' + result.stop_reason if result.stop_reason else ''})"
        )
    fit, val = split_validation(log, result)
    diag = diagnose_log(fit, cfg.vehicle, val)
    model = model_of(diag, "identification drive of a drawn truck (truckd sim --mixed)")
    return require_physical(model, "identification drive", "diagnosed model")


def _cached(path: Path) -> ModelFile | None:
    try:
        return read_model(path)
    except (InputError, TruckdError, OSError):
        return None  # absent or unreadable: diagnosed again, and written anew


def feedforward(p: VehicleParams) -> dict[str, float]:
    """SysId's kS (V), kV (V s/m), kA (V s^2/m) of the parameters ``p``."""
    ff = feedforward_of(p)
    return {"kS": ff.kS, "kV": ff.kV, "kA": ff.kA}


def tau_m(p: VehicleParams) -> float:
    """The mechanical time constant ``J_S R_m / (K_T K_v)`` (s)."""
    return p.J_S * p.R_m / (p.K_T * p.K_v)


def diagnosed_summary(model: ModelFile, truth: SimSetup) -> dict[str, Any]:
    """``trucks_diagnosed``'s entry: what the controller's model is, against the truth.

    ``m``, ``K_v``, ``K_T``, ``R_m``, ``J_S`` and ``effects`` (named, SI) as diagnosed;
    ``feedforward`` and ``feedforward_true`` (kS V, kV V s/m, kA V s^2/m),
    ``feedforward_relerr`` (diagnosed / true - 1); ``tau_m_s`` and ``tau_m_true_s``;
    ``input_delay_s`` and ``input_delay_true_s``.  The truth's constants are the drawn
    truck's seed parameters: with viscous friction b its voltage log shows a kV larger by
    ``R_m b / (K_T r)``, which the diagnosis (no current logged) folds into ``K_v``."""
    q, p = model.vehicle, truth.plant_params
    eff, true_eff = model.effects, truth.plant_config.effects
    ff, ff_true = feedforward(q), feedforward(p)
    return {
        "m": q.m,
        "K_v": q.K_v,
        "K_T": q.K_T,
        "R_m": q.R_m,
        "J_S": q.J_S,
        "effects": {n: getattr(eff, n) for n in eff.active()},
        "feedforward": ff,
        "feedforward_true": ff_true,
        "feedforward_relerr": {k: ff[k] / ff_true[k] - 1.0 for k in ff},
        "tau_m_s": tau_m(q),
        "tau_m_true_s": tau_m(p),
        "input_delay_s": eff.input_delay,
        "input_delay_true_s": true_eff.input_delay,
    }


class DiagnosedControllers:
    """``run_platoon``'s ``controllers`` (:data:`truckd.sim.platoon.Controllers`): each
    truck's controller on the model its own identification drive diagnoses.

    ``cfg`` the configuration (its ``vehicle:`` is the diagnosis's starting point, its
    ``characterize:`` section the drive); ``progress`` gets one line per truck;
    ``cache_dir`` keeps the models on disk (see the module docstring); ``workers`` above
    1: the trucks to diagnose are driven and diagnosed on that many forked processes
    (:class:`truckd.workers.ForkMap`; the same models)."""

    def __init__(
        self,
        cfg: TruckConfig,
        progress: Progress = _quiet,
        cache_dir: Path | None = None,
        workers: int = 1,
    ) -> None:
        self.cfg = cfg
        self.progress = progress
        self.cache_dir = cache_dir
        self.workers = workers
        self.diagnosed = 0
        """Trucks diagnosed (not found in the process's memo or the cache)."""

    def _path(self, key: str) -> Path | None:
        if self.cache_dir is None:
            return None
        digest = hashlib.sha256((code_digest() + "\n" + key).encode()).hexdigest()
        return self.cache_dir / f"{digest}.yaml"

    def _known(self, key: str) -> tuple[ModelFile, str] | None:
        """The model of an identification ``key`` found in the process's memo ("reused")
        or the disk cache ("cache"); None when it must be diagnosed."""
        if key in _MEMO:
            return _MEMO[key], "reused"
        path = self._path(key)
        hit = _cached(path) if path is not None else None
        if hit is None:
            return None
        _MEMO[key] = hit
        return hit, "cache"

    def _models(
        self, trucks: Sequence[SimSetup], done: Callable[[int, tuple[ModelFile, str, float]], None]
    ) -> list[tuple[ModelFile, str, float]]:
        """Each truck's model, where it came from and the seconds its identification
        took, ``done(i, that)`` as each is known (in order); the trucks to diagnose (one
        per identification) on the workers, all before the first is known, or here one
        after another.  _TruckDiagnosisError for the first truck whose diagnosis failed."""
        keys = [identification_key(identification_config(self.cfg, t)) for t in trucks]
        todo: dict[str, int] = {}
        found: dict[str, tuple[ModelFile, str]] = {}
        for i, key in enumerate(keys):
            if key not in todo and key not in found:
                known = self._known(key)
                if known is None:
                    todo[key] = i
                else:
                    found[key] = known

        def identify(i: int) -> tuple[ModelFile | None, str, float]:
            t0 = time.monotonic()
            try:
                return identify_truck(self.cfg, trucks[i]), "", time.monotonic() - t0
            except (TruckdError, InputError) as exc:
                return None, str(exc), time.monotonic() - t0

        firsts = list(todo.values())
        ran = {}
        if self.workers > 1 and len(firsts) > 1:
            ran = dict(zip(firsts, ForkMap(self.workers)(identify, firsts), strict=True))
        out: list[tuple[ModelFile, str, float]] = []
        for i, key in enumerate(keys):
            if todo.get(key) == i:
                model, error, secs = ran[i] if i in ran else identify(i)
                if model is None:
                    raise _TruckDiagnosisError(i, error)
                self.diagnosed += 1
                path = self._path(key)
                if path is not None:
                    write_model(path, model)
                _MEMO[key] = model
                out.append((model, "diagnosed", secs))
            else:  # found above (then an identical later truck: reused), or diagnosed above
                first = found.pop(key, None)
                out.append((*(first or (_MEMO[key], "reused")), 0.0))
            done(i, out[-1])
        return out

    def __call__(
        self, base: SimSetup, trucks: Sequence[SimSetup]
    ) -> list[tuple[SimSetup, dict[str, Any]]]:
        out: list[tuple[SimSetup, dict[str, Any]]] = []

        def done(i: int, got: tuple[ModelFile, str, float]) -> None:
            model, where, secs = got
            self.progress(f"truck{i} ({i + 1}/{len(trucks)}): model {where} ({secs:.1f} s)")
            cm = ControlModel(model.vehicle, model.effects)
            out.append((on_model(base, trucks[i], cm), diagnosed_summary(model, trucks[i])))

        try:
            self._models(trucks, done)
        except _TruckDiagnosisError as exc:
            raise TruckdError(
                f"truck{exc.truck}: its identification could not be diagnosed ({exc.why}); "
                "--true-models runs the controllers on the drawn trucks' true parameters"
            ) from None
        return out


class _TruckDiagnosisError(Exception):
    """The diagnosis of truck ``truck`` failed (``why``)."""

    def __init__(self, truck: int, why: str) -> None:
        super().__init__(why)
        self.truck, self.why = truck, why


def stderr_progress(msg: str) -> None:
    print(f"diagnosing the drawn trucks: {msg}", file=sys.stderr, flush=True)
