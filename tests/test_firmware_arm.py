"""The Cortex-M4 build of the firmware core and the STM32F4 board example:
`make -C firmware_protocol/firmware arm` with arm-none-eabi-gcc (warnings are errors).
A missing toolchain skips the build test with the install command in the summary
(``needs_tool``; CI installs it and fails instead, tests/tool_markers.py)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from firmware_protocol.fwcore import FIRMWARE_DIR

INSTALL = "apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi"


@pytest.mark.needs_tool("arm-none-eabi-gcc", install=INSTALL)
@pytest.mark.needs_tool("arm-none-eabi-objdump", install=INSTALL)
def test_arm_build_compiles_and_fits(tmp_path: Path) -> None:
    res = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE_DIR), f"BUILD={tmp_path}", "arm"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    sizes = re.findall(r"(truck_fw\w*\.elf): flash (\d+) bytes .*?, RAM (\d+) bytes", res.stdout)
    assert {s[0] for s in sizes} == {"truck_fw.elf", "truck_fw_can.elf"}, res.stdout
    for _, flash, ram in sizes:
        # an STM32F407 has 1 MiB flash and 128 KiB RAM; the core is meant to be small
        assert 1000 < int(flash) < 32 * 1024 and 4096 < int(ram) < 16 * 1024, res.stdout
    elf = tmp_path / "stm32f4" / "truck_fw.elf"
    head = elf.read_bytes()[:20]
    assert head[:4] == b"\x7fELF" and head[18] == 40  # e_machine EM_ARM
    # A fault switches the motor off (the fault handler used to spin with the last duty on
    # the motor), and the watchdog runs: its reload key is written in the main loop.
    dis = subprocess.run(
        ["arm-none-eabi-objdump", "-d", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    handler = dis.split("<Default_Handler>:", 1)[1].split("\n\n", 1)[0]
    assert "board_motor_off" in handler, handler
    assert "<board_motor_off>:" in dis
    assert "0xcccc" in dis and "0xaaaa" in dis  # IWDG start and reload keys


def test_missing_toolchain_is_an_error_naming_the_install(tmp_path: Path) -> None:
    res = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE_DIR), f"BUILD={tmp_path}", "ARM_PREFIX=no-such-", "arm"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert res.returncode != 0 and "apt-get install -y gcc-arm-none-eabi" in res.stderr
