"""Checks across sections: pairs of keys that pass one by one but cannot work together.

Each section validates its own keys (:func:`truckd.schema.load_dataclass`); what one section
asks of another, or of the firmware protocol (truck.dbc, :mod:`firmware_protocol.timing`), is
checked here, once, from :meth:`truckd.config.truck.TruckConfig.validate`: every command that
loads a configuration (``run``, ``sim``, ``characterize``, ``params``, ...) passes through
it.  A configuration that cannot work is refused with one line naming both keys (the CLI
exits 2).

The rules (``docs/reference.md``, "Configuration checks across sections"):

- ``control.rate_hz`` against the firmware's command timeout (MOTOR_CMD ``TruckTimeoutTime``):
  at least two commands per timeout, else the firmware switches the motor off between
  commands (at 8 Hz it applied 0 V in every cycle while the supervisor said ACTIVE);
- ``control.rate_hz`` against the companion heartbeat's period (``GenMsgCycleTime``): the
  cycle sends the heartbeat, so the period may not exceed it;
- ``runtime.stall_limit_s`` at least two control periods (a stall is a missed cycle);
- ``control.time_budget_s`` below the control period: a solve allowed the whole period or
  more overruns every cycle it uses it;
- ``platoon.plan_timeout_s`` at least two control periods (the predecessor publishes one plan
  a cycle: one late plan must not make it stale);
- freshness timeouts (``runtime.supervisor.*_timeout_s``, ``control.estimator.*_timeout_s``)
  at least two periods of the message they watch (truck.dbc), else a fresh sensor is stale;
- ``control.estimator.range_max`` within what RANGE.DISTANCE carries (truck.dbc);
- the spacing policy's gap at the speed limit (``control.d_0`` + headway x ``control.v_max``,
  the ACC headway ``platoon.acc_headway`` too when following a predecessor, or with
  ``platoon.order: auto``) within
  ``control.estimator.range_max``: else the lead leaves the sensor's range while followed;
- ``control.estimator.range_min`` below ``control.d_min``: the sensor must see the minimum
  gap;
- ``control.estimator.ticks_modulo`` and ``sample_time_modulo`` equal to the wrap of the
  signals they decode (truck.dbc);
- ``characterize`` voltages (``check_max_v``, ``step_voltages``, ``validation_v``) at most
  ``control.u_max``: the command is clipped there, the experiment would not be the one asked;
- ``control.u_max`` at most ``vehicle.V_batt``: the driver cannot apply more (a controller's
  model file with a higher ``V_batt`` then cannot raise the command above the battery);
- the truck (``vehicle``, the simulated one with ``plant.vehicle``, and a ``--model``
  file's, :func:`model_vehicle_problem`) breaks away below ``control.u_max``: a stiction
  above the stall torque at ``u_max`` holds it still while the motor draws its stall
  current.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from firmware_protocol.codec import specs
from firmware_protocol.timing import ProtocolTiming, timing

if TYPE_CHECKING:
    from truckd.config.truck import TruckConfig
    from truckd.model.params import VehicleParams

MIN_COMMANDS_PER_TIMEOUT = 2
"""Motor commands within the firmware's command timeout: one late or lost command must not
switch the motor off."""

MIN_PERIODS = 2
"""A freshness timeout spans at least this many periods of what it watches."""


def _g(x: float) -> str:
    return f"{x:.6g}"


def _rate_problems(cfg: TruckConfig, t: ProtocolTiming) -> str | None:
    c = cfg.control
    rate, period = c.rate_hz, c.period
    min_rate = MIN_COMMANDS_PER_TIMEOUT / t.cmd_timeout
    if rate < min_rate:
        return (
            f"key 'control.rate_hz' = {_g(rate)}: expected at least {_g(min_rate)} Hz, "
            f"{MIN_COMMANDS_PER_TIMEOUT} motor commands within the firmware's command timeout "
            f"(truck.dbc MOTOR_CMD TruckTimeoutTime {_g(t.cmd_timeout * 1e3)} ms), else it "
            "switches the motor off between commands"
        )
    if period > t.heartbeat_period:
        return (
            f"key 'control.rate_hz' = {_g(rate)}: expected at least "
            f"{_g(1.0 / t.heartbeat_period)} Hz, the companion heartbeat's rate (truck.dbc "
            f"COMPANION_HEARTBEAT GenMsgCycleTime {_g(t.heartbeat_period * 1e3)} ms): the "
            "control cycle sends it"
        )
    stall = cfg.runtime.stall_limit_s
    if stall < MIN_PERIODS * period:
        return (
            f"key 'runtime.stall_limit_s' = {_g(stall)}: expected at least two control "
            f"periods ({_g(MIN_PERIODS * period)} s at control.rate_hz {_g(rate)})"
        )
    if c.time_budget_s >= period:
        return (
            f"key 'control.time_budget_s' = {_g(c.time_budget_s)}: expected below the control "
            f"period ({_g(period)} s at control.rate_hz {_g(rate)}), else a solve that uses "
            "its budget overruns the cycle"
        )
    plan = cfg.platoon.plan_timeout_s
    if plan < MIN_PERIODS * period:
        return (
            f"key 'platoon.plan_timeout_s' = {_g(plan)}: expected at least two control periods "
            f"({_g(MIN_PERIODS * period)} s at control.rate_hz {_g(rate)}): a plan comes once "
            "a cycle"
        )
    return None


def _freshness_problems(cfg: TruckConfig, t: ProtocolTiming) -> str | None:
    sup, est = cfg.runtime.supervisor, cfg.control.estimator
    fastest = min(p for p in t.periods.values() if p > 0)
    watched = (
        ("runtime.supervisor.encoder_timeout_s", sup.encoder_timeout_s, "WHEEL_ENCODERS"),
        ("runtime.supervisor.range_timeout_s", sup.range_timeout_s, "RANGE"),
        ("control.estimator.encoder_timeout_s", est.encoder_timeout_s, "WHEEL_ENCODERS"),
        ("control.estimator.lead_timeout_s", est.lead_timeout_s, "RANGE"),
    )
    for key, value, msg in watched:
        need = MIN_PERIODS * t.periods[msg]
        if value < need:
            return (
                f"key '{key}' = {_g(value)}: expected at least {_g(need)} s, two periods of "
                f"{msg} (truck.dbc GenMsgCycleTime {_g(t.periods[msg] * 1e3)} ms)"
            )
    if sup.link_timeout_s < MIN_PERIODS * fastest:
        return (
            f"key 'runtime.supervisor.link_timeout_s' = {_g(sup.link_timeout_s)}: expected at "
            f"least {_g(MIN_PERIODS * fastest)} s, two periods of the most frequent message "
            f"(truck.dbc GenMsgCycleTime {_g(fastest * 1e3)} ms)"
        )
    return None


def _range_problems(cfg: TruckConfig) -> str | None:
    c, est = cfg.control, cfg.control.estimator
    rng = specs()["RANGE"]
    distance_max = rng.raw_range["DISTANCE"][1] * rng.scale["DISTANCE"]
    if est.range_max > distance_max:
        return (
            f"key 'control.estimator.range_max' = {_g(est.range_max)}: expected at most "
            f"{_g(distance_max)} m, the largest distance RANGE.DISTANCE carries (truck.dbc)"
        )
    headways = [("control.time_headway", c.time_headway)]
    if cfg.platoon.predecessor or cfg.platoon.order == "auto":  # a follower, or may be
        headways += [
            ("platoon.cacc_headway", cfg.platoon.cacc_headway),
            ("platoon.acc_headway", cfg.platoon.acc_headway),
        ]
    key, h = max(headways, key=lambda kv: kv[1])
    gap = c.d_0 + h * c.v_max
    if gap >= est.range_max:
        return (
            f"key 'control.estimator.range_max' = {_g(est.range_max)}: expected above the "
            f"gap kept at the speed limit, control.d_0 + {key} x control.v_max = "
            f"{_g(c.d_0)} + {_g(h)} x {_g(c.v_max)} = {_g(gap)} m, else the lead leaves the "
            "sensor's range while followed"
        )
    if est.range_min >= c.d_min:
        return (
            f"key 'control.estimator.range_min' = {_g(est.range_min)}: expected below "
            f"control.d_min ({_g(c.d_min)} m): the sensor must see the minimum gap"
        )
    return None


def _wrap_problems(cfg: TruckConfig) -> str | None:
    est = cfg.control.estimator
    enc = specs()["WHEEL_ENCODERS"]
    lo, hi = enc.raw_range["TICKS_LEFT"]
    ticks = hi - lo + 1
    if est.ticks_modulo != ticks:
        return (
            f"key 'control.estimator.ticks_modulo' = {est.ticks_modulo}: expected {ticks}, "
            "the wrap of WHEEL_ENCODERS.TICKS_LEFT (truck.dbc)"
        )
    lo, hi = enc.raw_range["SAMPLE_TIME"]
    wrap = (hi - lo + 1) * enc.scale["SAMPLE_TIME"]
    if not math.isclose(est.sample_time_modulo, wrap, rel_tol=1e-9):
        return (
            f"key 'control.estimator.sample_time_modulo' = {_g(est.sample_time_modulo)}: "
            f"expected {_g(wrap)} s, the wrap of WHEEL_ENCODERS.SAMPLE_TIME (truck.dbc)"
        )
    return None


def _characterize_problems(cfg: TruckConfig) -> str | None:
    ch, u_max = cfg.characterize, cfg.control.u_max
    volts = [
        ("characterize.check_max_v", ch.check_max_v),
        *((f"characterize.step_voltages[{k}]", v) for k, v in enumerate(ch.step_voltages)),
        ("characterize.validation_v", ch.validation_v),
    ]
    for key, v in volts:
        if v > u_max:
            return (
                f"key '{key}' = {_g(v)}: expected at most control.u_max ({_g(u_max)} V): the "
                "command is clipped there"
            )
    return None


def _supply_problems(cfg: TruckConfig) -> str | None:
    u_max, v_batt = cfg.control.u_max, cfg.vehicle.V_batt
    if u_max > v_batt:
        return (
            f"key 'control.u_max' = {_g(u_max)}: expected at most vehicle.V_batt "
            f"({_g(v_batt)} V): the driver cannot apply more than the battery gives"
        )
    return None


def _stuck(key: str, p: VehicleParams, u_max: float) -> str | None:
    """Why the truck ``p`` (``key`` names it) cannot move under ``u_max`` volts: its
    stiction at least the stall torque ``K_T u_max / R_m`` (None: it can)."""
    stall = p.K_T * u_max / p.R_m
    if p.K_stiction >= stall:
        return (
            f"{key}.K_stiction = {_g(p.K_stiction)} N m: at least the stall torque "
            f"at control.u_max ({_g(stall)} N m, K_T u_max / R_m): the truck cannot move"
        )
    return None


def model_vehicle_problem(cfg: TruckConfig, p: VehicleParams, source: str) -> str | None:
    """:func:`_stuck` for a controller's model file's vehicle ``p`` (``source`` names
    it): a model fitted to the truck describes it."""
    return _stuck(f"{source}: vehicle", p, cfg.control.u_max)


def _truck_problems(cfg: TruckConfig) -> str | None:
    u_max = cfg.control.u_max
    why = _stuck("vehicle", cfg.vehicle, u_max)
    if why is None and cfg.plant.vehicle.given():
        why = _stuck("plant.vehicle", cfg.plant_vehicle, u_max)
    return why


def cross_section_problem(cfg: TruckConfig, t: ProtocolTiming | None = None) -> str | None:
    """The first pair of keys that cannot work together (one line naming both), or None.
    ``t``: the protocol's timing (truck.dbc's by default)."""
    t = t if t is not None else timing()
    return (
        _rate_problems(cfg, t)
        or _freshness_problems(cfg, t)
        or _range_problems(cfg)
        or _wrap_problems(cfg)
        or _characterize_problems(cfg)
        or _supply_problems(cfg)
        or _truck_problems(cfg)
    )
