"""systemd/truckd.service: `systemd-analyze verify` clean, security exposure under 2.5,
and the directives the daemon relies on present."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parent.parent / "systemd" / "truckd.service"
EXPOSURE_THRESHOLD = 2.5  # systemd-analyze security scale 0 (locked down) .. 10 (exposed)


pytestmark = pytest.mark.needs_tool("systemd-analyze", install="apt-get install -y systemd")
"""Every check here runs systemd-analyze (tests/tool_markers.py: skipped when missing,
failed in CI)."""


def installed_copy(tmp_path: Path, text: str | None = None) -> Path:
    """The unit with ExecStart pointing at this environment's truckd (verify checks it)."""
    truckd = Path(sys.executable).parent / "truckd"
    assert truckd.exists(), "the truckd console script must be installed in the venv"
    src = UNIT.read_text() if text is None else text
    out = tmp_path / "truckd.service"
    out.write_text(src.replace("/usr/local/bin/truckd", str(truckd)))
    return out


def directives(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        k, _, v = line.partition("=")
        out.setdefault(k.strip(), []).append(v.strip())
    return out


def test_verify_is_clean(tmp_path: Path) -> None:
    p = installed_copy(tmp_path)
    r = subprocess.run(["systemd-analyze", "verify", str(p)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == "", r.stderr


def test_verify_catches_a_broken_unit(tmp_path: Path) -> None:
    # the check above can fail: a typo in a directive is reported
    p = installed_copy(tmp_path, UNIT.read_text().replace("Type=notify", "Type=notfy"))
    r = subprocess.run(["systemd-analyze", "verify", str(p)], capture_output=True, text=True)
    assert "notfy" in r.stderr


def test_security_exposure_under_threshold(tmp_path: Path) -> None:
    p = installed_copy(tmp_path)
    r = subprocess.run(
        ["systemd-analyze", "security", "--offline=yes", str(p)], capture_output=True, text=True
    )
    m = re.search(r"Overall exposure level for truckd\.service: ([0-9.]+)", r.stdout)
    assert m is not None, r.stdout + r.stderr
    assert float(m.group(1)) < EXPOSURE_THRESHOLD
    thr = subprocess.run(
        ["systemd-analyze", "security", "--offline=yes",
         f"--threshold={int(EXPOSURE_THRESHOLD * 10)}", str(p)],
        capture_output=True,
        text=True,
    )  # fmt: skip
    assert thr.returncode == 0


def test_unit_has_what_the_daemon_needs() -> None:
    d = directives(UNIT.read_text())
    assert d["Type"] == ["notify"]
    assert d["Restart"] == ["on-failure"]
    assert d["WatchdogSec"] and d["WatchdogSec"][0] != "0"
    assert d["ProtectSystem"] == ["strict"]
    assert d["NoNewPrivileges"] == ["yes"]
    assert d.get("DynamicUser") == ["yes"] or "User" in d
    assert "dialout" in d["SupplementaryGroups"][0]
    assert any("ttyACM" in x for x in d["DeviceAllow"])
    assert "AF_CAN" in d["RestrictAddressFamilies"][0].split()
    assert "AF_UNIX" in d["RestrictAddressFamilies"][0].split()  # sd_notify
    assert d["LimitRTPRIO"] and int(d["LimitRTPRIO"][0]) >= 50  # rt_priority default
    assert d["LimitMEMLOCK"] == ["infinity"]
    assert "RestrictRealtime" not in d or d["RestrictRealtime"] == ["no"]
    assert "run --config" in d["ExecStart"][0]
    assert d["KillSignal"] == ["SIGTERM"]
