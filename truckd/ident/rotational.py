"""The diagnosis's words for a rotating machine (a SysId log in rad, rad/s).

The diagnosis fits a rotating machine's speed (rad/s) where a truck's speed (m/s) would
stand, with nothing scaled: numerically a speed is then in rad/s, a distance in rad and a
force in N m (a force times a speed is a power, and the speed's number is the shaft's
rad/s: the number is the torque at the measured shaft).  :func:`in_rotational_units`
relabels the units of a note written for a truck, the numbers unchanged.  Pure text.
"""

from __future__ import annotations

import re

_RELABEL = (
    (re.compile(r"(\d) m/s\^2\b"), r"\1 rad/s^2"),
    (re.compile(r"(\d) m/s\b"), r"\1 rad/s"),
    (re.compile(r"(\d) N\b(?! m\b)(?! s/)"), r"\1 N m"),
    (re.compile(r"(\d) m\b(?![/^])"), r"\1 rad"),
)
"""A number's unit as a truck's note writes it, and the rotating machine's."""


def in_rotational_units(text: str) -> str:
    """``text`` (a note for a truck) with each number's m/s^2, m/s, N and m said as the
    rotating machine's rad/s^2, rad/s, N m and rad; a motor's N m, V s/rad and kg m^2
    stay as they are."""
    for pattern, unit in _RELABEL:
        text = pattern.sub(unit, text)
    return text
