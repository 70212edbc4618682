"""JSON schemas of the telemetry messages (reference section 5), for MCAP and Foxglove.

One schema per channel kind: ``state``, ``health``, ``plan``.  They describe what the
daemon publishes (``truckd/runtime/daemon.py``): the contract's keys are required, the
extras are described, further keys are allowed (``additionalProperties``) so an older
reader keeps working when a message grows.  Units are in each field's description.  No
clock, no I/O: data only.
"""

from __future__ import annotations

import json
from typing import Any

KINDS = ("state", "health", "plan")
"""Channel kinds, in the order the recorder registers them."""

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

_NUM_OR_NULL = ["number", "null"]
_MODES = ["INIT", "ACTIVE", "DEGRADED", "SAFE_STOP", "FAULT"]


def _num(desc: str) -> dict[str, Any]:
    return {"type": _NUM_OR_NULL, "description": desc}


STATE: dict[str, Any] = {
    "title": "truckd.State",
    "description": "One control cycle (truckd/<vehicle_id>/state). null: not available "
    "this cycle (no lead tracked, controller not run).",
    "type": "object",
    "properties": {
        "seq": {"type": "integer", "minimum": 0, "description": "cycle number"},
        "t": {"type": "number", "description": "time since the loop started, s"},
        "mode": {"type": "string", "enum": _MODES, "description": "supervisor mode"},
        "v": _num("estimated speed, m/s"),
        "gap": _num("estimated gap to the lead, m"),
        "gap_ref": _num("reference gap d_0 + h v, m"),
        "v_lead": _num("estimated lead speed, m/s"),
        "u": {"type": "number", "description": "motor voltage command sent, V"},
        "u_ff": _num("feedforward part of the command, V"),
        "solve_us": _num("MPC solve time (OSQP's own), us"),
        "enable": {"type": "boolean", "description": "motor driver enabled"},
        "ctrl": {"type": ["string", "null"], "description": "controller mode"},
        "fallback": {"type": ["string", "null"], "description": "why the MPC was not used"},
        "lead_valid": {"type": "boolean", "description": "a lead is tracked"},
        "lateness_us": _num("wake-up lateness of this cycle, us"),
        "faults": {"type": "array", "items": {"type": "string"}, "description": "causes"},
        "ages_ms": {
            "type": "object",
            "additionalProperties": {"type": _NUM_OR_NULL},
            "description": "age of the newest link/encoder/range data, ms",
        },
    },
    "required": ["seq", "t", "mode", "v", "gap", "gap_ref", "v_lead", "u", "u_ff", "solve_us"],
    "additionalProperties": True,
}

_LOOP = {
    "type": "object",
    "description": "RateKeeper statistics (lateness and compute in us)",
    "properties": {
        k: _num(k.replace("_us_", " us ").replace("_", " "))
        for k in (
            "cycles",
            "misses",
            "skipped_periods",
            "lateness_us_p50",
            "lateness_us_p99",
            "lateness_us_max",
            "compute_us_p50",
            "compute_us_p99",
            "compute_us_max",
        )
    },
    "additionalProperties": True,
}

HEALTH: dict[str, Any] = {
    "title": "truckd.Health",
    "description": "Health of one vehicle (truckd/<vehicle_id>/health), at least 1 Hz and on "
    "every mode transition.",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "time since the loop started, s"},
        "mode": {"type": "string", "enum": _MODES, "description": "supervisor mode"},
        "faults": {"type": "array", "items": {"type": "string"}},
        "transitions": {"type": "array", "items": {"type": "object"}},
        "loop": _LOOP,
        "link": {"type": "object", "description": "link and receive-check counters"},
        "ages_s": {"type": "object", "additionalProperties": {"type": _NUM_OR_NULL}},
        "firmware": {"type": "object"},
        "controller": {"type": "object"},
        "telemetry": {"type": ["object", "null"]},
        "recorder": {"type": ["object", "null"]},
        "realtime": {"type": "object"},
        "state_rate_hz": _num("state messages per second"),
        "pid": {"type": "integer"},
    },
    "required": ["t", "mode", "faults"],
    "additionalProperties": True,
}

PLAN: dict[str, Any] = {
    "title": "truckd.Plan",
    "description": "The controller's plan this cycle (truckd/<vehicle_id>/plan).",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "time of the plan's first step, s"},
        "seq": {"type": "integer", "minimum": 0, "description": "cycle number"},
        "dt": {"type": "number", "exclusiveMinimum": 0, "description": "step, s"},
        "v": {
            "type": "array",
            "items": {"type": _NUM_OR_NULL},
            "description": "predicted speed over the horizon, m/s",
        },
        "a": {
            "type": "array",
            "items": {"type": _NUM_OR_NULL},
            "description": "predicted acceleration over the horizon, m/s^2",
        },
    },
    "required": ["t", "seq", "dt", "v", "a"],
    "additionalProperties": True,
}

SCHEMAS: dict[str, dict[str, Any]] = {"state": STATE, "health": HEALTH, "plan": PLAN}


def schema_bytes(kind: str) -> bytes:
    """The schema of ``kind`` as compact JSON bytes (an MCAP Schema record's data)."""
    return json.dumps(SCHEMAS[kind], separators=(",", ":")).encode()


def topic(vehicle_id: str, kind: str) -> str:
    """The MCAP/Foxglove topic: ``/truckd/<vehicle_id>/<kind>``."""
    return f"/truckd/{vehicle_id}/{kind}"
