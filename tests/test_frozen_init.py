"""truckd.control.frozen.fast_init: the same instances as a frozen dataclass's generated
constructor (fields, order, defaults, equality, hash, still frozen), and a refusal of
what it cannot do exactly."""

from __future__ import annotations

import dataclasses
import inspect
import math

import pytest

from truckd.control.estimator import EncoderSample, Estimate, RangeSample
from truckd.control.frozen import fast_init
from truckd.control.mpc import MpcResult
from truckd.control.output import ControlOutput
from truckd.control.platoon import Plan
from truckd.control.qp import QpInputs
from truckd.control.supervisor import Decision, SupervisorInputs
from truckd.runtime.cycle import CycleOutputs

FAST = (EncoderSample, RangeSample, Estimate, MpcResult, ControlOutput, Plan, QpInputs,
        SupervisorInputs, Decision, CycleOutputs)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class _Plain:
    a: float
    b: tuple[float, ...]
    c: str = "x"
    d: float = math.nan


@fast_init
@dataclasses.dataclass(frozen=True)
class _Fast:
    a: float
    b: tuple[float, ...]
    c: str = "x"
    d: float = math.nan


def _params(cls: type) -> list[tuple[str, object]]:
    sig = inspect.signature(cls.__init__)  # type: ignore[misc]
    return [(p.name, p.default) for p in list(sig.parameters.values())[1:]]


def test_same_instances_as_the_generated_constructor() -> None:
    assert _params(_Fast) == _params(_Plain)
    for args, kw in [((1.0, (2.0,)), {}), ((1.0, ()), {"d": 3.0}), ((), {"b": (), "a": 0.5})]:
        fast, plain = _Fast(*args, **kw), _Plain(*args, **kw)
        assert list(vars(fast).items()) == list(vars(plain).items())
        assert fast == _Fast(*args, **kw) and hash(fast) == hash(_Fast(*args, **kw))
        assert repr(fast).removeprefix("_Fast") == repr(plain).removeprefix("_Plain")
    f = _Fast(1.0, (2.0,))
    with pytest.raises(dataclasses.FrozenInstanceError):
        f.a = 2.0  # type: ignore[misc]
    assert dataclasses.replace(f, c="y") == _Fast(1.0, (2.0,), "y")
    with pytest.raises(TypeError):
        _Fast(1.0)  # type: ignore[call-arg]


def test_project_records_keep_their_fields() -> None:
    """Each record built every cycle: the constructor's parameters are its fields in
    order, with the declared defaults."""
    for cls in FAST:
        want = [
            (f.name, f.default if f.default is not dataclasses.MISSING else inspect.Parameter.empty)
            for f in dataclasses.fields(cls)
        ]
        assert _params(cls) == want, cls.__name__


def test_refuses_what_it_cannot_do_exactly() -> None:
    @dataclasses.dataclass
    class Mutable:
        a: float

    @dataclasses.dataclass(frozen=True, slots=True)
    class Slots:
        a: float

    @dataclasses.dataclass(frozen=True)
    class Factory:
        a: list[float] = dataclasses.field(default_factory=list)

    @dataclasses.dataclass(frozen=True)
    class Post:
        a: float

        def __post_init__(self) -> None:
            pass

    for cls in (Mutable, Slots, Factory, Post):
        with pytest.raises(TypeError):
            fast_init(cls)
