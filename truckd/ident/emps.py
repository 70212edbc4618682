"""The EMPS benchmark data (real measurements) as contract force-input logs.

The rig's two MATLAB files ship with the repository in ``tests/data/emps`` (their README
gives provenance and licence); the environment variable ``TRUCKD_EMPS_DIR`` names another
directory.  :func:`emps_log` turns one into a
:class:`truckd.logfile.Log` with ``t`` (s), ``F = gtau * vir`` (N, load side), ``x``
(m, measured position) and the reference ``x_ref`` (m); ``python -m truckd.ident.emps
OUTDIR [DATADIR]`` writes both as CSV.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from truckd.errors import InputError
from truckd.logfile import Log, write_log

TRAIN = "DATA_EMPS.mat"
TEST = "DATA_EMPS_PULSES.mat"


def emps_dir() -> Path:
    """Where the EMPS files are: ``$TRUCKD_EMPS_DIR`` or the checkout's ``tests/data/emps``."""
    env = os.environ.get("TRUCKD_EMPS_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "tests" / "data" / "emps"


def emps_log(name: str, directory: Path | None = None) -> Log:
    """One EMPS file as a force-input log (raises InputError when missing)."""
    from scipy.io import loadmat

    path = (directory or emps_dir()) / name
    if not path.is_file():
        raise InputError(f"{path}: EMPS data file not found (set TRUCKD_EMPS_DIR)")
    d = loadmat(str(path))
    cols = {
        "t": np.asarray(d["t"], float).ravel(),
        "F": float(np.asarray(d["gtau"]).item()) * np.asarray(d["vir"], float).ravel(),
        "x": np.asarray(d["qm"], float).ravel(),
        "x_ref": np.asarray(d["qg"], float).ravel(),
    }
    return Log(cols, str(path))


def main(argv: list[str] | None = None) -> int:
    """Write ``emps_train.csv`` and ``emps_test.csv`` into the directory given (first
    argument), read from the EMPS directory given second (default :func:`emps_dir`)."""
    args = sys.argv[1:] if argv is None else argv
    out = Path(args[0] if args else ".")
    data = Path(args[1]) if len(args) > 1 else None
    out.mkdir(parents=True, exist_ok=True)
    for name, csv in ((TRAIN, "emps_train.csv"), (TEST, "emps_test.csv")):
        write_log(out / csv, emps_log(name, data).columns)
        print(f"{name} -> {out / csv}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
