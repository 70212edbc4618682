"""The rules that accept a cause, call two causes ambiguous, or a residual unexplained.

One source for both diagnoses (voltage input: simulation error; force input: inverse
dynamics).  Costs are weighted sums of squared residuals (in units of the noise
variance for the voltage path).  Pure numerics.
"""

from __future__ import annotations

import numpy as np

from truckd.ident.residuals import Whiteness

BIC_MIN = 10.0
"""Decrease of the information criterion a candidate must bring (strong evidence)."""
REL_MIN = 0.05
"""Relative decrease of the validation cost a candidate must bring."""
AMBIGUOUS = 0.05
"""Two candidates whose validation costs differ by less than this fraction (and that do
not combine) are ambiguous."""
ACF_MAX = 0.2
"""Residual is called structured when more than this fraction of lags is outside the band."""
STRUCT_MIN = 0.5
"""... and its RMS beyond the noise exceeds this multiple of the noise level."""
EXPLAINS_RMS = 3.0
"""A white residual explains the data only at the noise level: its RMS within this many
noise levels (a few wild samples, white but far above the noise, do not)."""


def delta_bic(sse_new: float, sse_old: float, n: int, extra: int) -> float:
    """Change of the Bayesian information criterion for ``extra`` more parameters."""
    ratio = max(sse_new, 1e-300) / max(sse_old, 1e-300)
    return n * float(np.log(ratio)) + extra * float(np.log(n))


def passes(dbic: float, val_new: float, val_old: float) -> bool:
    """A candidate earns its place: strong evidence on the estimation data *and* a
    validation cost lower by at least :data:`REL_MIN`."""
    return dbic < -BIC_MIN and val_new < (1.0 - REL_MIN) * val_old


def close(a: float, b: float, absolute: float = 2.0 * BIC_MIN) -> bool:
    """Two validation costs the data cannot tell apart (:data:`AMBIGUOUS`, or within
    ``absolute`` noise units)."""
    return abs(a - b) < max(absolute, AMBIGUOUS * min(a, b))


def structured(wt: Whiteness, noise: float, floor: float) -> bool:
    """Structure remains in a residual: many lags of its autocorrelation *or* of its
    cross-correlation with the input outside the white-noise band, *and* RMS beyond the
    noise above ``max(STRUCT_MIN noise, floor)``."""
    corr = wt.acf_outside > ACF_MAX or wt.ccf_outside > ACF_MAX
    return bool(corr and wt.structure > max(STRUCT_MIN * noise, floor))


def at_noise_level(wt: Whiteness, noise: float, floor: float) -> bool:
    """The residual's RMS is within :data:`EXPLAINS_RMS` noise levels (or ``floor``)."""
    return bool(wt.rms <= max(EXPLAINS_RMS * noise, floor))


def white(wt: Whiteness) -> bool:
    """The residual is white and independent of the input: few lags of its
    autocorrelation and of its cross-correlation with the input outside the band."""
    return bool(wt.acf_outside <= ACF_MAX and wt.ccf_outside <= ACF_MAX)
