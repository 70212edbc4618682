"""``diagnose --report DIR``: index.html with PNG plots and the table of candidates.

Plots (seed model and extended model): measured against simulated speed; the residual
over time; the residual against speed, acceleration, input, current and position
(binned means with 99 % bands); the residual's autocorrelation and its
cross-correlation with the input, with the 99 % band of white noise.
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np

from truckd.errors import TruckdError
from truckd.ident.residuals import autocorr, band, binned, crosscorr
from truckd.ident.result import Diagnosis, Traces


def write_report(diag: Diagnosis, out_dir: str | Path, source: str) -> Path:
    """Write the report; returns the path of index.html."""
    try:
        import matplotlib
    except ImportError:
        raise TruckdError(
            "--report needs matplotlib (install the 'plot' extra: pip install 'truckd[plot]')"
        ) from None
    matplotlib.use("Agg")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images: list[tuple[str, str]] = []
    tr = diag.traces
    speed = diag.units()[0]
    if tr is not None:
        images.append(("Measured and simulated speed", _plot_fit(tr, out / "fit.png", speed)))
        images.append(("Residual over time", _plot_residual_time(tr, out / "residual.png", speed)))
        images.append(
            (
                "Residual against the signals",
                _plot_residual_vs(tr, out / "residual_vs.png", speed),
            )
        )
        images.append(("Autocorrelation and cross-correlation with the input", _plot_corr(tr, out)))
    index = out / "index.html"
    index.write_text(_html(diag, images, source), encoding="utf-8")
    (out / "diagnosis.json").write_text(json.dumps(diag.to_json(), indent=2), encoding="utf-8")
    return index


def _fig(rows: int, cols: int = 1, h: float = 3.0) -> tuple[Any, Any]:
    import matplotlib.pyplot as plt

    return plt.subplots(rows, cols, figsize=(10, h * rows), squeeze=False)


def _save(fig: Any, path: Path) -> str:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path.name


def _plot_fit(tr: Traces, path: Path, speed: str = "m/s") -> str:
    fig, ax = _fig(2)
    ax[0, 0].plot(tr.t, tr.y, "k", lw=0.8, label="measured")
    ax[0, 0].plot(tr.t, tr.y_base, "C1", lw=0.8, label="seed model")
    ax[0, 0].plot(tr.t, tr.y_ext, "C0", lw=0.8, label="extended model")
    ax[0, 0].set_ylabel(f"speed ({speed})")
    ax[0, 0].legend(loc="upper right")
    ax[1, 0].plot(tr.t, tr.inp, "C2", lw=0.8)
    ax[1, 0].set_ylabel("voltage (V)" if tr.input_name == "u" else "force (N)")
    ax[1, 0].set_xlabel("time (s)")
    return _save(fig, path)


def _plot_residual_time(tr: Traces, path: Path, speed: str = "m/s") -> str:
    fig, ax = _fig(1)
    ax[0, 0].plot(tr.t, tr.y - tr.y_base, "C1", lw=0.6, label="seed model")
    ax[0, 0].plot(tr.t, tr.y - tr.y_ext, "C0", lw=0.6, label="extended model")
    ax[0, 0].set_ylabel(f"measured - simulated ({speed})")
    ax[0, 0].set_xlabel("time (s)")
    ax[0, 0].legend(loc="upper right")
    return _save(fig, path)


def _signals(tr: Traces, speed: str = "m/s") -> list[tuple[str, np.ndarray]]:
    h = np.gradient(tr.t)
    acc = np.gradient(tr.y_ext) / h
    x = tr.x if tr.x is not None else np.concatenate([[0.0], np.cumsum(tr.y[:-1] * np.diff(tr.t))])
    out = [
        (f"speed ({speed})", tr.y_ext),
        (f"acceleration, simulated ({speed}^2)", acc),
        ("voltage command (V)" if tr.input_name == "u" else "force (N)", tr.inp),
        (f"position ({speed.removesuffix('/s')})", x),
    ]
    if tr.i is not None:
        out.insert(3, ("current (A)", tr.i))
    return out


def _plot_residual_vs(tr: Traces, path: Path, speed: str = "m/s") -> str:
    sig = _signals(tr, speed)
    fig, ax = _fig(len(sig), 1, 2.4)
    for k, (name, x) in enumerate(sig):
        a = ax[k, 0]
        for r, col, lab in ((tr.y - tr.y_base, "C1", "seed"), (tr.y - tr.y_ext, "C0", "extended")):
            b = binned(x, r)
            a.errorbar(b.centers, b.mean, yerr=b.half_width, fmt="o-", ms=3, color=col, label=lab)
        a.axhline(0.0, color="k", lw=0.5)
        a.set_xlabel(name)
        a.set_ylabel(f"mean residual ({speed})")
    ax[0, 0].legend(loc="upper right")
    return _save(fig, path)


def _plot_corr(tr: Traces, out: Path) -> str:
    n = len(tr.y)
    lag = max(10, min(n // 4, 200))
    fig, ax = _fig(2)
    lags = np.arange(lag + 1)
    clags = np.arange(-lag, lag + 1)
    for r, col, lab in ((tr.y - tr.y_base, "C1", "seed"), (tr.y - tr.y_ext, "C0", "extended")):
        ax[0, 0].plot(lags[1:], autocorr(r, lag)[1:], col, lw=0.8, label=lab)
        ax[1, 0].plot(clags, crosscorr(r, tr.inp, lag), col, lw=0.8, label=lab)
    for a in (ax[0, 0], ax[1, 0]):
        a.axhline(band(n), color="k", ls="--", lw=0.6)
        a.axhline(-band(n), color="k", ls="--", lw=0.6)
    ax[0, 0].set_ylabel("residual autocorrelation")
    ax[0, 0].set_xlabel("lag (samples); dashed: 99 % band of white noise")
    ax[1, 0].set_ylabel("cross-corr. with input")
    ax[1, 0].set_xlabel("lag (samples)")
    ax[0, 0].legend(loc="upper right")
    return _save(fig, out / "correlation.png")


def _fmt(params: dict[str, float]) -> str:
    return ", ".join(f"{k} = {v:.4g}" for k, v in params.items())


def _html(diag: Diagnosis, images: list[tuple[str, str]], source: str) -> str:
    e = html.escape
    rows = "".join(
        f"<tr><td>{e(c.name)}</td><td>{e(_fmt(c.params))}</td><td>{c.fit_percent:.2f}</td>"
        f"<td>{c.gain_percent:+.2f}</td><td>{c.cost_ratio:.3f}</td><td>{c.delta_bic:.1f}</td>"
        f"<td>{'yes' if c.accepted else 'no'}</td><td>{e(c.note)}</td></tr>"
        for c in diag.candidates
    )
    found = "".join(
        f"<li><b>{e(f.name)}</b>: {e(_fmt(f.params))}; fit {f.fit_percent:.2f} % "
        f"({f.fit_gain_percent:+.2f})</li>"
        for f in diag.effects
    ) or (
        "<li>none: the residual is white at the noise level</li>"
        if diag.explains
        else "<li>none among the candidates</li>"
    )
    force = ""
    if diag.baseline.force_relerr_percent is not None:
        force = (
            f"<p>Force relative error (inverse dynamics): seed "
            f"{diag.baseline.force_relerr_percent:.3f} %, extended "
            f"{diag.extended.force_relerr_percent:.3f} %</p>"
        )
    ls = diag.least_squares
    if ls is not None and ls.get("fit_percent") is not None:
        u = diag.units()[1:]
        force += (
            f"<p>Least squares (WPILib SysId's model, the data's own): fit "
            f"{ls['fit_percent']:.2f} %, kS {ls['kS']:.4g} {u[0]}, kV {ls['kV']:.4g} {u[1]}, "
            f"kA {ls['kA']:.4g} {u[2]}.</p>"
        )
    if diag.fit_ceiling is not None:
        force += (
            f"<p>Noise ceiling: fit {diag.fit_ceiling:.2f} % (a model that leaves only the "
            "speed's measurement noise).</p>"
        )
    if diag.alerts:
        force += "<ul>" + "".join(f"<li><b>{e(a)}</b></li>" for a in diag.alerts) + "</ul>"
    imgs = "".join(f"<h2>{e(t)}</h2><img src='{e(p)}' alt='{e(t)}'>" for t, p in images)
    notes = "".join(f"<li>{e(n)}</li>" for n in diag.notes)
    amb = ", ".join(f"{a} / {b}" for a, b in diag.ambiguous) or "none"
    return f"""<!doctype html><html><head><meta charset='utf-8'>
<title>truckd diagnose: {e(source)}</title>
<style>body{{font-family:sans-serif;max-width:1000px}}td,th{{border:1px solid #ccc;
padding:3px 6px}}table{{border-collapse:collapse}}img{{max-width:100%}}</style></head><body>
<h1>Diagnosis of {e(source)}</h1>
<p>{diag.samples} samples, {e(diag.input)} input. Seed model fit
{diag.baseline.fit_percent:.2f} % (RMSE {diag.baseline.rmse:.4g}); extended model fit
{diag.extended.fit_percent:.2f} % (RMSE {diag.extended.rmse:.4g}).</p>{force}
<h2>Causes found</h2><ul>{found}</ul>
<p>Ambiguous pairs: {e(amb)}. Structure left unexplained:
<b>{"yes" if diag.unexplained else "no"}</b>.</p>
<h2>Candidates (each alone on top of the seed, validation data)</h2>
<table><tr><th>candidate</th><th>parameters</th><th>fit %</th><th>gain</th>
<th>cost ratio</th><th>&Delta;BIC</th><th>accepted</th><th>note</th></tr>{rows}</table>
<h2>Seed model: {e(_fmt(diag.baseline.params))}</h2>
<h2>Extended model: {e(_fmt(diag.extended.params))}</h2>
<h2>What the data can determine</h2><ul>{notes}</ul>
{imgs}
</body></html>
"""
