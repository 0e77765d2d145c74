"""deploy/systemd: the unit passes `systemd-analyze verify` with no complaint (the check is shown to
complain about a broken copy), stays well hardened, and its user file and example config parse."""

from __future__ import annotations

import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

SYSTEMD = Path(__file__).resolve().parents[1] / "deploy" / "systemd"
UNIT = SYSTEMD / "meniscope.service"
#: Most exposed `systemd-analyze security` may rate the unit (0 = locked down, 10 = unprotected).
MAX_EXPOSURE = 2.5


def _analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.skip("systemd-analyze not found (Debian package systemd)")
    return exe


def _verify(unit_text: str, root: Path) -> subprocess.CompletedProcess:
    """`systemd-analyze verify` of ``unit_text`` in a root of this host's units with ExecStart's program stubbed."""
    units = root / "usr/lib/systemd/system"
    if not units.exists():
        shutil.copytree("/usr/lib/systemd/system", units, symlinks=True)
    exe = root / re.search(r"^ExecStart=(\S+)", unit_text, re.M).group(1).lstrip("/")
    exe.parent.mkdir(parents=True, exist_ok=True)
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    (root / "etc/systemd/system").mkdir(parents=True, exist_ok=True)
    (root / "etc/systemd/system/meniscope.service").write_text(unit_text)
    return subprocess.run(
        [_analyze(), "verify", f"--root={root}", "meniscope.service"], capture_output=True, text=True, timeout=60
    )


def test_the_unit_verifies_without_a_complaint(tmp_path: Path) -> None:
    if not Path("/usr/lib/systemd/system/multi-user.target").exists():
        pytest.skip("this host has no systemd units to verify against")
    result = _verify(UNIT.read_text(), tmp_path)
    assert result.returncode == 0 and not (result.stdout + result.stderr).strip(), result.stdout + result.stderr


def test_verify_would_catch_a_typo(tmp_path: Path) -> None:
    """The check above can fail: systemd ignores an unknown key with a warning (status 0), which it reports."""
    if not Path("/usr/lib/systemd/system/multi-user.target").exists():
        pytest.skip("this host has no systemd units to verify against")
    broken = UNIT.read_text().replace("ProtectHome=yes", "ProtectHomes=yes")
    result = _verify(broken, tmp_path)
    assert "Unknown key 'ProtectHomes'" in result.stdout + result.stderr


def test_the_unit_is_hardened() -> None:
    result = subprocess.run(
        [_analyze(), "security", "--offline=yes", "--no-pager", str(UNIT)], capture_output=True, text=True, timeout=60
    )
    match = re.search(r"Overall exposure level for meniscope.service: ([\d.]+)", result.stdout + result.stderr)
    if match is None:
        pytest.skip(f"this systemd-analyze has no offline security check: {result.stderr.strip()[:200]}")
    assert float(match.group(1)) <= MAX_EXPOSURE, result.stdout


def test_the_unit_runs_as_its_own_user_and_restarts() -> None:
    text = UNIT.read_text()
    for line in (
        "User=meniscope",
        "Restart=on-failure",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "StateDirectory=meniscope",
        "--config /etc/meniscope/config.toml",
    ):
        assert line in text, line
    assert "MemoryDenyWriteExecute=yes" not in text, "numba's JIT needs writable executable memory"


def test_the_sysusers_file_makes_the_user(tmp_path: Path) -> None:
    exe = shutil.which("systemd-sysusers")
    if exe is None:
        pytest.skip("systemd-sysusers not found (Debian package systemd)")
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc/passwd").write_text("root:x:0:0::/root:/bin/sh\n")
    (tmp_path / "etc/group").write_text("root:x:0:\nvideo:x:44:\n")
    result = subprocess.run(
        [exe, f"--root={tmp_path}", "--dry-run", str(SYSTEMD / "meniscope.sysusers.conf")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert "Creating user 'meniscope'" in result.stdout + result.stderr


def test_the_example_config_is_toml_with_the_service_settings() -> None:
    config = tomllib.loads((SYSTEMD / "config.example.toml").read_text())
    assert set(config) <= {"source", "host", "port", "token", "data_dir"} and config["port"] == 8000
