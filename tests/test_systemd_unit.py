"""The service unit as systemd's own tools judge it, and the installer in a scratch tree.

The unit is checked the way the README promises: `systemd-analyze verify` clean and
`systemd-analyze security` exposure at most 2.0. The installer runs for real into tmp_path
(root=), so idempotence and "never overwrite a lab's config" are tested, not assumed.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from leveler.daemon import install
from leveler.daemon.install import InstallError, install_service, render_unit

REPO = Path(__file__).resolve().parents[1]
VENV_LEVELER = Path(sys.prefix) / "bin" / "leveler"
MAX_EXPOSURE = 2.0

needs_analyze = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None,
    reason="systemd-analyze missing: apt-get install systemd (make systemd-deps)")


@pytest.fixture
def unit_file(tmp_path: Path) -> Path:
    """The canonical unit, with an ExecStart that exists here (verify checks it)."""
    config = tmp_path / "leveler.toml"
    config.write_text((REPO / "config" / "lab.toml").read_text())
    path = tmp_path / "leveler.service"
    path.write_text(render_unit(str(VENV_LEVELER), str(config)))
    return path


def analyze(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["systemd-analyze", *args], capture_output=True, text=True,
                          timeout=60, cwd=cwd)


def settings(unit: str) -> dict[str, list[str]]:
    """KEY -> every value it is given, across sections (enough for this flat unit)."""
    out: dict[str, list[str]] = {}
    for line in unit.splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


@needs_analyze
def test_unit_verifies_clean(unit_file: Path) -> None:
    assert VENV_LEVELER.exists(), "run from the project venv (make test)"
    res = analyze("verify", str(unit_file), cwd=unit_file.parent)
    about_unit = [ln for ln in (res.stdout + res.stderr).splitlines() if "leveler" in ln]
    assert res.returncode == 0 and not about_unit, res.stdout + res.stderr
    # The same check does catch a broken unit: an ExecStart that does not exist.
    missing = unit_file.with_name("missing.service")
    missing.write_text(render_unit("/nonexistent/leveler", "/etc/leveler/leveler.toml"))
    assert analyze("verify", str(missing), cwd=unit_file.parent).returncode != 0


@needs_analyze
def test_security_exposure_at_most_2(unit_file: Path) -> None:
    res = analyze("security", "--offline=true", "--threshold=20", str(unit_file),
                  cwd=unit_file.parent)
    m = re.search(r"Overall exposure level for leveler\.service: (\d+\.\d+)", res.stdout)
    assert m, res.stdout + res.stderr
    assert res.returncode == 0 and float(m.group(1)) <= MAX_EXPOSURE, res.stdout


def test_unit_keeps_the_daemon_contract() -> None:
    """The settings the daemon relies on, and the ones that would break it, stated once."""
    s = settings(render_unit("/opt/leveler/bin/leveler", "/etc/leveler/leveler.toml"))
    for key, value in {"Type": "notify", "WatchdogSec": "10s", "Restart": "on-failure",
                       "KillSignal": "SIGTERM", "TimeoutStopSec": "15s", "User": "leveler",
                       "CPUSchedulingPolicy": "fifo", "LimitMEMLOCK": "infinity",
                       "ProtectSystem": "strict", "RestrictAddressFamilies": "AF_UNIX",
                       "ExecReload": "/bin/kill -HUP $MAINPID"}.items():
        assert s.get(key) == [value], key
    assert s["ExecStart"] == ["/opt/leveler/bin/leveler run --config /etc/leveler/leveler.toml"]
    assert s["DeviceAllow"] == ["char-ttyS rw", "char-ttyUSB rw", "char-ttyACM rw"]
    assert set(s["CapabilityBoundingSet"][0].split()) == {"CAP_SYS_NICE", "CAP_IPC_LOCK"}
    # SCHED_FIFO, serial ports and the logs must stay possible.
    assert "RestrictRealtime" not in s and "PrivateDevices" not in s
    assert s["StateDirectory"] == ["leveler leveler/logs"]


def test_render_unit_substitutes_paths_and_refuses_unsafe_ones() -> None:
    s = settings(render_unit("/srv/lv/bin/leveler", "/srv/conf/lv.toml", user="lv", group="lab"))
    assert s["ExecStart"] == ["/srv/lv/bin/leveler run --config /srv/conf/lv.toml"]
    assert s["ReadWritePaths"] == ["/srv/conf"]
    assert (s["User"], s["Group"], s["SupplementaryGroups"]) == (["lv"], ["lab"], ["dialout"])
    for bad in ("relative/leveler", "/with space/leveler", "/x/%n", "/x/$HOME"):
        with pytest.raises(InstallError):
            render_unit(bad, "/etc/leveler/leveler.toml")
    with pytest.raises(InstallError):
        render_unit("/opt/leveler/bin/leveler", "/etc/leveler/leveler.toml", user="a b")


@pytest.fixture
def system_python() -> str:
    """An interpreter the installer accepts for the service's venv, or skip."""
    try:
        install._check_python("/usr/bin/python3")
    except InstallError as exc:
        pytest.skip(str(exc))
    return "/usr/bin/python3"


def test_dry_run_lists_every_step_and_changes_nothing(tmp_path: Path, system_python: str) -> None:
    lines = install_service(root=tmp_path, dry_run=True, python=system_python)
    text = "\n".join(lines)
    for step in (f"would create group leveler: groupadd --system --prefix {tmp_path} leveler",
                 "would create user leveler: useradd --system --no-create-home",
                 "--shell /usr/sbin/nologin --gid leveler --groups dialout",
                 f"would create venv /opt/leveler with {system_python}",
                 f"would pip install {REPO} into /opt/leveler (versions pinned by "
                 "config/constraints.txt)",
                 "would copy config/lab.toml to /etc/leveler/leveler.toml",
                 "would write unit /etc/systemd/system/leveler.service",
                 "systemctl enable --now leveler"):
        assert step in text, text
    assert list(tmp_path.iterdir()) == []


def test_dry_run_reports_an_existing_config_as_kept(tmp_path: Path, system_python: str) -> None:
    (tmp_path / "etc" / "leveler").mkdir(parents=True)
    (tmp_path / "etc" / "leveler" / "leveler.toml").write_text("# the lab's\n")
    lines = install_service(root=tmp_path, dry_run=True, python=system_python)
    assert "config /etc/leveler/leveler.toml: kept as it is (never overwritten)" in lines
    assert not any("copy config/lab.toml" in ln for ln in lines)


def fake_prefix(root: Path) -> None:
    """Stands in for the venv (building one is a network install, not what is tested here)."""
    exe = root / "opt" / "leveler" / "bin" / "leveler"
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)


def test_install_into_a_tree_is_idempotent_and_never_overwrites_config(tmp_path: Path) -> None:
    fake_prefix(tmp_path)
    first = install_service(root=tmp_path, create_user=False, build_venv=False)
    config = tmp_path / "etc" / "leveler" / "leveler.toml"
    unit = tmp_path / "etc" / "systemd" / "system" / "leveler.service"
    assert config.read_text() == (REPO / "config" / "lab.toml").read_text()
    assert unit.read_text() == render_unit("/opt/leveler/bin/leveler",
                                           "/etc/leveler/leveler.toml")
    assert (config.stat().st_mode & 0o777, config.parent.stat().st_mode & 0o777,
            unit.stat().st_mode & 0o777) == (0o640, 0o750, 0o644)
    assert "config /etc/leveler/leveler.toml: copied from config/lab.toml" in first
    assert "unit /etc/systemd/system/leveler.service: written" in first
    # written atomically (a temporary file renamed into place): nothing else left beside them
    assert [p.name for p in config.parent.iterdir()] == ["leveler.toml"]
    assert [p.name for p in unit.parent.iterdir()] == ["leveler.service"]

    config.write_text("# tuned by the lab\n")
    second = install_service(root=tmp_path, create_user=False, build_venv=False)
    assert config.read_text() == "# tuned by the lab\n"
    assert "config /etc/leveler/leveler.toml: kept as it is (never overwritten)" in second
    assert "unit /etc/systemd/system/leveler.service: unchanged" in second


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("useradd") is None,
                    reason="useradd --prefix needs root and the shadow tools")
def test_creates_user_and_group_in_the_tree_only(tmp_path: Path) -> None:
    etc = tmp_path / "etc"
    etc.mkdir()
    for name in ("passwd", "group", "shadow", "gshadow", "login.defs"):
        if Path("/etc", name).exists():
            shutil.copy2(Path("/etc", name), etc / name)
    host_passwd = Path("/etc/passwd").read_text()
    if "\nleveler:" in "\n" + (etc / "passwd").read_text():
        pytest.skip("this machine already has a leveler user: nothing would be created")
    fake_prefix(tmp_path)
    lines = install_service(root=tmp_path, build_venv=False)
    assert "created group leveler" in lines and "created user leveler" in lines
    pw = next(r.split(":") for r in (etc / "passwd").read_text().splitlines()
              if r.startswith("leveler:"))
    assert pw[5:] == ["/var/lib/leveler", "/usr/sbin/nologin"]
    groups = {r.split(":")[0]: r.split(":") for r in (etc / "group").read_text().splitlines()}
    assert groups["leveler"][2] == pw[3]
    assert "leveler" in groups["dialout"][3].split(",")
    config = etc / "leveler" / "leveler.toml"
    assert (config.stat().st_uid, config.stat().st_gid) == (int(pw[2]), int(pw[3]))
    assert Path("/etc/passwd").read_text() == host_passwd
    again = install_service(root=tmp_path, build_venv=False)
    assert "group leveler: exists" in again and "user leveler: exists" in again


def test_refuses_to_install_on_this_machine_without_root(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(install.os, "geteuid", lambda: 1000)
    with pytest.raises(InstallError, match="needs root"):
        install_service()
    assert install_service(root=tmp_path, dry_run=True, create_user=False, build_venv=False)


def test_refuses_an_interpreter_the_sandbox_hides(tmp_path: Path) -> None:
    with pytest.raises(InstallError, match="ProtectHome"):
        install_service(root=tmp_path, dry_run=True, python="/home/someone/.pyenv/bin/python3")
    assert list(tmp_path.iterdir()) == []


def test_the_constraints_pin_every_runtime_dependency_within_its_bounds() -> None:
    """make install takes the tested versions; a pin outside pyproject's bounds (say mcap,
    whose internals the writer relies on) would fail the install, not the test."""
    import importlib.metadata

    from packaging.requirements import Requirement

    pins = {}
    for line in (REPO / "config" / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[name.lower().replace("_", "-")] = version
    for text in importlib.metadata.requires("lab-leveler") or []:
        req = Requirement(text)
        if req.marker is not None:  # an extra's
            continue
        version = pins.get(req.name.lower().replace("_", "-"))
        assert version is not None, f"{req.name} is not pinned"
        assert req.specifier.contains(version), f"{req.name}=={version} outside {req.specifier}"


@needs_analyze
def test_the_live_network_drop_in_opens_loopback_only_and_stays_within_2(
        unit_file: Path) -> None:
    """systemd/live-network.conf (docs/live.md): the unit with it applied still verifies,
    keeps its exposure at most 2.0, and allows IP to localhost alone."""
    drop = (REPO / "systemd" / "live-network.conf").read_text()
    assert settings(drop)["IPAddressAllow"] == ["localhost"]
    assert settings(drop)["IPAddressDeny"] == ["any"]
    merged = unit_file.parent / "merged" / "leveler.service"
    merged.parent.mkdir()
    merged.write_text(unit_file.read_text() + "\n" + drop)  # a drop-in's lines come last
    res = analyze("verify", str(merged), cwd=unit_file.parent)
    assert res.returncode == 0, res.stdout + res.stderr
    res = analyze("security", "--offline=true", "--threshold=20", str(merged),
                  cwd=merged.parent)
    m = re.search(r"Overall exposure level for leveler\.service: (\d+\.\d+)", res.stdout)
    assert m and float(m.group(1)) <= MAX_EXPOSURE, res.stdout + res.stderr
    assert "Service may allocate Internet sockets" in res.stdout  # the drop-in took effect
