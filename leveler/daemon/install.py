"""`sudo make install`: leveler as a hardened systemd service (systemd/leveler.service).

Every step checks before it acts, so running it again only repeats what is needed, and a
lab's /etc/leveler/leveler.toml is never overwritten. `root=` installs into another tree
(tests, images): users are then created with `useradd --prefix`, and nothing is started.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path

from leveler.daemon.persist import write_atomic

SOURCE = Path(__file__).resolve().parents[2]  # the checkout: leveler/daemon/install.py
UNIT_NAME = "leveler.service"
STATE_DIR = "/var/lib/leveler"
# The canonical unit names these; render_unit() substitutes the installed paths.
_EXEC = "ExecStart=/opt/leveler/bin/leveler run --config /etc/leveler/leveler.toml"
_CONFIG_RW = "ReadWritePaths=/etc/leveler"
_USER, _GROUP = "User=leveler", "Group=leveler"
# Paths go into a unit file unquoted: no spaces, quotes, '%' specifiers or '$' expansions.
_PLAIN_PATH = re.compile(r"/[A-Za-z0-9._+@/-]*")
_NAME = re.compile(r"[a-z_][a-z0-9_-]{0,31}")
# ProtectHome=yes hides these from the service: an interpreter there cannot start it.
_HOMES = (Path("/home"), Path("/root"), Path("/run/user"))
# Never copied into the build: the developer's venv, VCS data, build leftovers, logs.
_NOT_SOURCE = shutil.ignore_patterns(".venv", ".git", "build", "*.egg-info", "__pycache__",
                                     ".pytest_cache", ".ruff_cache", "logs", "*.mcap")


class InstallError(Exception):
    """A step that cannot be done; the message says what to do instead."""


def render_unit(exec_path: str, config_path: str, *, user: str = "leveler",
                group: str = "leveler", source: Path = SOURCE) -> str:
    """The canonical unit with ExecStart=, the writable config directory and the identity."""
    for path in (exec_path, config_path):
        if not _PLAIN_PATH.fullmatch(path):
            raise InstallError(f"{path!r}: need an absolute path of letters, digits and ._+@-")
    for name in (user, group):
        if not _NAME.fullmatch(name):
            raise InstallError(f"{name!r}: not a system user or group name")
    text = (source / "systemd" / UNIT_NAME).read_text()
    subst = {_EXEC: f"ExecStart={exec_path} run --config {config_path}",
             _CONFIG_RW: f"ReadWritePaths={Path(config_path).parent}",
             _USER: f"User={user}", _GROUP: f"Group={group}"}
    for line, new in subst.items():
        if len(re.findall(f"^{re.escape(line)}$", text, flags=re.M)) != 1:
            raise InstallError(f"systemd/{UNIT_NAME} no longer has exactly one {line!r}")
        text = re.sub(f"^{re.escape(line)}$", new, text, flags=re.M)
    return text


def _under(root: Path, path: str) -> Path:
    """`path` (absolute, as the installed system sees it) inside the tree at `root`."""
    return root / Path(path).relative_to("/")


def _run(cmd: Sequence[str]) -> None:
    try:
        subprocess.run(cmd, check=True, capture_output=True, text=True)
    except FileNotFoundError:
        raise InstallError(f"{cmd[0]}: not found") from None
    except subprocess.CalledProcessError as exc:
        raise InstallError(f"{' '.join(cmd)} failed: {exc.stderr.strip()}") from None


def _entries(file: Path) -> dict[str, list[str]]:
    """name -> fields of a passwd/group style file (empty if the file does not exist)."""
    if not file.exists():
        return {}
    rows = (line.split(":") for line in file.read_text().splitlines() if line.strip())
    return {row[0]: row for row in rows}


def _ids(root: Path, user: str, group: str) -> tuple[int, int] | None:
    """uid and gid of user and group in the tree at `root`, None if either is missing."""
    pw = _entries(root / "etc" / "passwd").get(user)
    gr = _entries(root / "etc" / "group").get(group)
    return (int(pw[2]), int(gr[2])) if pw and gr else None


def _check_python(python: str) -> None:
    """The venv links to this interpreter, so the sandboxed service must be able to run it."""
    real = Path(python).resolve()
    if any(real.is_relative_to(home) for home in _HOMES):
        raise InstallError(f"{python} is {real}, which ProtectHome=yes hides from the service: "
                           "use a system interpreter (--python /usr/bin/python3.11)")
    try:
        check = "import sys, ensurepip; sys.exit(sys.version_info < (3, 11))"
        subprocess.run([python, "-c", check], check=True, capture_output=True)
    except (OSError, subprocess.CalledProcessError):
        raise InstallError(f"{python}: need Python >= 3.11 with venv "
                           "(apt-get install python3 python3-venv)") from None


#: The versions `make test` last passed with (`make constraints` writes it): the service
#: gets those, not whatever the package index serves on the day of the install.
CONSTRAINTS = Path("config") / "constraints.txt"


def _pip_install(venv_python: Path, source: Path) -> None:
    """Install a copy of the source tree, so the build leaves no root-owned files in it,
    with the tested versions (CONSTRAINTS) when the tree has them."""
    with tempfile.TemporaryDirectory(prefix="leveler-install-") as tmp:
        src = Path(tmp) / "src"
        shutil.copytree(source, src, ignore=_NOT_SOURCE)
        pinned = ["-c", str(src / CONSTRAINTS)] if (src / CONSTRAINTS).is_file() else []
        _run([str(venv_python), "-m", "pip", "install", "--quiet", "--upgrade", *pinned,
              str(src)])


def install_service(*, prefix: str = "/opt/leveler", config_dir: str = "/etc/leveler",
                    unit_dir: str = "/etc/systemd/system", user: str = "leveler",
                    group: str = "leveler", dry_run: bool = False, root: Path = Path("/"),
                    source: Path = SOURCE, python: str = "/usr/bin/python3",
                    create_user: bool = True, build_venv: bool = True) -> list[str]:
    """Install the service; returns what was done (or, with dry_run, what would be done).

    create_user=False leaves users alone (a test tree without /etc/passwd); build_venv=False
    uses the venv already at `prefix` (venvs are not relocatable, so one cannot be built
    into another root).
    """
    root = Path(root)
    on_host = root == Path("/")
    if not dry_run and on_host and os.geteuid() != 0:
        raise InstallError("installing a system service needs root: sudo make install "
                           "(or --dry-run to see the steps)")
    if build_venv and not on_host and not dry_run:
        raise InstallError("a venv cannot be built into another root: build_venv=False")
    lines: list[str] = []

    def step(done: str, planned: str, action: Callable[[], object]) -> None:
        if dry_run:
            lines.append(f"would {planned}")
        else:
            action()
            lines.append(done)

    at_root = [] if on_host else ["--prefix", str(root)]
    if not create_user:
        lines.append(f"user {user} and group {group}: left alone (create_user=False)")
    else:
        if group in _entries(root / "etc" / "group"):
            lines.append(f"group {group}: exists")
        else:
            cmd = ["groupadd", "--system", *at_root, group]
            step(f"created group {group}", f"create group {group}: {' '.join(cmd)}",
                 lambda: _run(cmd))
        if user in _entries(root / "etc" / "passwd"):
            lines.append(f"user {user}: exists")
        else:
            cmd = ["useradd", "--system", "--no-create-home", "--home-dir", STATE_DIR,
                   "--shell", "/usr/sbin/nologin", "--gid", group, "--groups", "dialout",
                   *at_root, user]
            step(f"created user {user}", f"create user {user}: {' '.join(cmd)}",
                 lambda: _run(cmd))

    venv_python = _under(root, prefix) / "bin" / "python"
    if build_venv:
        _check_python(python)
        if venv_python.exists():
            lines.append(f"venv {prefix}: exists")
        else:
            step(f"created venv {prefix} ({python})", f"create venv {prefix} with {python}",
                 lambda: _run([python, "-m", "venv", str(_under(root, prefix))]))
        pins = (f" (versions pinned by {CONSTRAINTS})" if (source / CONSTRAINTS).is_file()
                else " (no constraints file: the index's newest versions)")
        step(f"installed {source} into {prefix}{pins}",
             f"pip install {source} into {prefix}{pins}",
             lambda: _pip_install(venv_python, source))
    elif dry_run or (_under(root, prefix) / "bin" / "leveler").exists():
        lines.append(f"venv {prefix}: used as it is (build_venv=False)")
    else:
        raise InstallError(f"{prefix}/bin/leveler does not exist (build_venv=False)")

    ids = None if dry_run else _ids(root, user, group)
    cdir = _under(root, config_dir)
    config = cdir / "leveler.toml"

    def own(path: Path, mode: int) -> None:
        path.chmod(mode)
        if ids is not None and os.geteuid() == 0:
            os.chown(path, *ids)

    def make_config_dir() -> None:
        cdir.mkdir(parents=True, exist_ok=True)
        own(cdir, 0o750)

    def copy_config() -> None:  # atomic: a crash never leaves a half config to be kept
        lab = (source / "config" / "lab.toml").read_text()
        write_atomic(config, lab.replace('group = "leveler"', f'group = "{group}"'),
                     lambda tmp: tomllib.loads(tmp.read_text()), mode=0o640)
        own(config, 0o640)

    # The daemon's user owns the directory: `leveler tune --persist` renames a file into it.
    step(f"config directory {config_dir}: {user}:{group} 0750",
         f"make config directory {config_dir} ({user}:{group} 0750)", make_config_dir)
    if config.exists():
        lines.append(f"config {config_dir}/leveler.toml: kept as it is (never overwritten)")
    else:
        step(f"config {config_dir}/leveler.toml: copied from config/lab.toml",
             f"copy config/lab.toml to {config_dir}/leveler.toml", copy_config)

    unit = _under(root, unit_dir) / UNIT_NAME
    text = render_unit(f"{prefix}/bin/leveler", f"{config_dir}/leveler.toml", user=user,
                       group=group, source=source)
    if unit.exists() and unit.read_text() == text:
        lines.append(f"unit {unit_dir}/{UNIT_NAME}: unchanged")
    else:
        def write_unit() -> None:
            unit.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(unit, text, lambda tmp: None, mode=0o644)

        step(f"unit {unit_dir}/{UNIT_NAME}: written", f"write unit {unit_dir}/{UNIT_NAME}",
             write_unit)

    if not on_host:
        lines.append(f"installed into {root}: on that system, systemctl enable --now leveler")
    elif Path("/run/systemd/system").is_dir():
        step("systemctl daemon-reload: done", "run systemctl daemon-reload",
             lambda: _run(["systemctl", "daemon-reload"]))
        lines.append("start it, and at every boot: systemctl enable --now leveler "
                     "(running already? systemctl restart leveler)")
    else:
        lines.append("systemd is not running here: once it is, systemctl enable --now leveler")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m leveler.daemon.install`: what `make install` runs."""
    parser = argparse.ArgumentParser(prog="leveler-install", description=__doc__.split("\n")[0])
    parser.add_argument("--dry-run", action="store_true", help="print the steps, change nothing")
    parser.add_argument("--prefix", default="/opt/leveler", help="venv to create and run from")
    parser.add_argument("--python", default="/usr/bin/python3",
                        help="interpreter for the venv (not under /home or /root)")
    args = parser.parse_args(argv)
    try:
        lines = install_service(prefix=args.prefix, python=args.python, dry_run=args.dry_run)
    except InstallError as exc:
        print(f"leveler install: error: {exc}", file=sys.stderr)
        return 2
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
