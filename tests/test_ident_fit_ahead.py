"""Fits done ahead of their turn on the workers (the greedy joint refits): each reached
later is not fitted again, says its own progress lines where the plain loop would, and
one never reached says nothing; with the plain loop nothing is fitted ahead."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from types import SimpleNamespace
from typing import Any, TypeVar, cast

import pytest

from truckd.ident import choice
from truckd.ident.candidates import Candidate
from truckd.ident.fanout import in_order
from truckd.ident.voltage import FitResult, Param
from truckd.workers import ForkMap, can_fork

T = TypeVar("T")
R = TypeVar("R")

PARAMS = {n: Param(n, 1.0, 0.0, 10.0) for n in ("a", "b", "c", "d")}
CANDS = {n: Candidate(n, PARAMS[n], (0.0, 1.0)) for n in PARAMS}


def _base(sse: float) -> FitResult:
    return cast(FitResult, SimpleNamespace(sse=sse, name="base"))


def _selecting(mapper: Any, said: list[str]) -> choice._Selecting:
    """A selection whose fits are stubs: each says two lines naming itself."""
    prep = SimpleNamespace(fit_data=[], w=None, val_data=[])
    seed = SimpleNamespace(free=[], grid=())
    return choice._Selecting(
        cast(Any, prep),
        cast(Any, seed),
        cast(Any, None),
        said.append,
        cast(Any, None),
        mapper=mapper,
    )


@pytest.fixture
def stub_fits(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    fits: list[str] = []

    def fit_candidate(
        base: FitResult, free: object, extra: list[Param], cand: Candidate, *a: object
    ) -> FitResult:
        say = cast(Callable[[str], None], a[3])
        tag = f"{cand.name}+{[p.name for p in extra]}"
        fits.append(tag)
        say(f"  fit {tag}: first")
        say(f"  fit {tag}: second")
        return cast(FitResult, SimpleNamespace(sse=base.sse - len(tag), tag=tag))

    monkeypatch.setattr(choice, "fit_candidate", fit_candidate)
    return fits


def _side_by_side(fn: Callable[[T], R], items: Sequence[T], /) -> list[R]:
    """A mapper that is not the plain loop (the same results, in order)."""
    return [fn(x) for x in reversed(items)][::-1]


def _run(s: choice._Selecting, ahead: bool) -> list[object]:
    top = _base(100.0)
    extra = [PARAMS["a"]]
    if ahead:
        s.fit_ahead([(top, extra, CANDS[n]) for n in ("b", "c", "d")])
    out: list[object] = [s.fit_all([(top, extra, CANDS["b"], "joint refit: a + b")])[0]]
    out.append(s.fit_all([(top, extra, CANDS["c"], "joint refit: a + c")])[0])
    out.append(s.fit_all([(top, extra, CANDS["c"], "again: a + c")])[0])
    return out  # d was fitted ahead and never reached


def test_fits_done_ahead_read_as_the_plain_loop(stub_fits: list[str]) -> None:
    plain_said: list[str] = []
    plain = _run(_selecting(in_order, plain_said), ahead=True)
    plain_fits = list(stub_fits)
    stub_fits.clear()
    said: list[str] = []
    ahead = _run(_selecting(_side_by_side, said), ahead=True)
    assert [vars(x) for x in ahead] == [vars(x) for x in plain]
    assert said == plain_said
    assert "  fit d+['a']: first" not in said  # fitted ahead, never reached: not said
    assert plain_fits == ["b+['a']", "c+['a']"]  # the plain loop fits nothing ahead
    assert sorted(stub_fits) == ["b+['a']", "c+['a']", "d+['a']"]  # each once, d wasted
    assert said.count("  c with ['a'] freed: fitted above") == 1


def test_a_fit_ahead_whose_start_changed_is_fitted_again(stub_fits: list[str]) -> None:
    """The guess was wrong (another model became the start): the fit runs at its turn."""
    said: list[str] = []
    s = _selecting(_side_by_side, said)
    s.fit_ahead([(_base(100.0), [PARAMS["a"]], CANDS[n]) for n in ("b", "c")])
    other = _base(90.0)
    got = s.fit_all([(other, [PARAMS["a"]], CANDS["b"], None)])[0]
    assert stub_fits.count("b+['a']") == 2
    assert got.sse == 90.0 - len("b+['a']")
    assert said == ["  fit b+['a']: first", "  fit b+['a']: second"]


def test_a_fit_done_already_is_not_fitted_ahead(stub_fits: list[str]) -> None:
    s = _selecting(_side_by_side, [])
    top = _base(100.0)
    s.fit_all([(top, [PARAMS["a"]], CANDS["b"], None)])
    s.fit_ahead([(top, [PARAMS["a"]], CANDS[n]) for n in ("b", "c", "d")])
    assert sorted(stub_fits) == ["b+['a']", "c+['a']", "d+['a']"]


def test_nothing_is_fitted_ahead_where_the_fits_would_run_one_after_another(
    stub_fits: list[str],
) -> None:
    """Workers that cannot fork here (another thread runs) run the fits in this process:
    a guess would cost this process's time."""

    class Here:
        def side_by_side(self) -> bool:
            return False

        def __call__(self, fn: Callable[[T], R], items: Sequence[T], /) -> list[R]:
            return [fn(x) for x in items]

    s = _selecting(Here(), [])
    s.fit_ahead([(_base(100.0), [PARAMS["a"]], CANDS[n]) for n in ("b", "c", "d")])
    assert stub_fits == []


def test_workers_say_whether_they_run_side_by_side() -> None:
    assert ForkMap(2).side_by_side() == can_fork()
    assert not ForkMap(1).side_by_side()
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not ForkMap(2).side_by_side()  # a lock held at the fork would stay held
    finally:
        stop.set()
        other.join()
