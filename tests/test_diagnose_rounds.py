"""The selection's rounds on top of the accepted causes (``choice._extra_rounds``), with
the fits and the judge stood in for: which candidates each round tries."""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import pytest

from truckd.ident import choice
from truckd.ident.scoring import Model
from truckd.ident.voltage import FitResult


def _fit(sse: float) -> FitResult:
    return FitResult(params=None, effects=None, sse=sse, n=1, nfev=0)  # type: ignore[arg-type]


@dataclass
class _Rounds:
    """A selection whose fits give each candidate the cost ratio of ``ratios`` (its fit's
    cost over the current model's), recording the candidates each round fits."""

    ratios: dict[str, float]
    tried: list[list[str]] = field(default_factory=list)

    def fit_all(self, jobs: list[tuple[Any, ...]]) -> list[FitResult]:
        self.tried.append([cand.name for _, _, cand, _ in jobs])
        return [_fit(base.sse * self.ratios[cand.name]) for base, _, cand, _ in jobs]


def _selection(rounds: _Rounds) -> SimpleNamespace:
    judge = SimpleNamespace(
        takes=lambda name, new, old: (new.fit.sse < 0.8 * old.fit.sse, 0.0),
        possible=lambda fit, names: True,
    )
    cands = [SimpleNamespace(name=n) for n in rounds.ratios]
    return SimpleNamespace(
        accepted=["first"],
        ambiguous=[],
        current=Model(_fit(1.0), ("first",), 1.0),
        prep=SimpleNamespace(val_data=[], w=None),
        trials=SimpleNamespace(cands=cands, judge=judge),
        smooth_params=lambda names: [],
        fit_all=rounds.fit_all,
        note=lambda *args, **kwargs: None,
    )


@pytest.fixture(autouse=True)
def _structure_always_remains(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(choice, "_structure_remains", lambda s: True)
    monkeypatch.setattr(choice, "val_cost", lambda f, val, w: f.sse)


def test_a_candidate_that_changed_nothing_is_not_tried_in_the_next_round() -> None:
    """Round 1: ``helps`` halves the cost and is taken, ``idle`` changes it by less than
    IDLE_GAIN, ``weak`` lowers it a little; round 2 tries ``weak`` again, not ``idle``."""
    rounds = _Rounds({"idle": 1.0 - 0.1 * choice.IDLE_GAIN, "helps": 0.5, "weak": 0.95})
    s = _selection(rounds)
    choice._extra_rounds(s)  # type: ignore[arg-type]
    assert rounds.tried == [["idle", "helps", "weak"], ["weak"]]
    assert s.accepted == ["first", "helps"]


def test_a_round_with_nothing_left_to_try_ends_the_rounds() -> None:
    """Every candidate but the one taken was idle: no second round is fitted."""
    rounds = _Rounds({"idle": 1.0, "helps": 0.5})
    s = _selection(rounds)
    choice._extra_rounds(s)  # type: ignore[arg-type]
    assert rounds.tried == [["idle", "helps"]]
    assert s.accepted == ["first", "helps"]
