"""The README's tour edits the shipped configuration with ``sed`` to hide a cause in the
simulated truck: the edit must still change exactly that effect, or the tour's
``characterize`` run finds nothing to find."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def test_the_tours_slope_edit_hides_exactly_that_load_force() -> None:
    readme = (ROOT / "README.md").read_text()
    m = re.search(r"^\s*sed 's/(.+?)/(.+?)/' config/truck\.yaml > out/slope\.yaml$", readme, re.M)
    assert m is not None, "the tour's sed line is gone from README.md"
    pattern, replacement = m.group(1), m.group(2)
    shipped = (ROOT / "config" / "truck.yaml").read_text()
    edited, n = re.subn(pattern, replacement, shipped, flags=re.M)  # sed's per-line ^ and $
    assert n == 1, f"the tour's sed edits {n} lines of config/truck.yaml"
    before, after = yaml.safe_load(shipped), yaml.safe_load(edited)
    assert before["plant"]["effects"]["load_force"] == 0.0
    assert after["plant"]["effects"]["load_force"] == 1.5
    after["plant"]["effects"]["load_force"] = 0.0
    assert after == before  # nothing else changed
