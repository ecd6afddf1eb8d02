"""Truncated, bit-flipped, zero-filled and foreign files given to `replay`, `diagnose` and
`asd` (issue 8, "bad input"): a clear one-line error and exit 2, or exit 0 with a note that
the log was incomplete and how to make a complete copy; never a traceback.

The damage is placed by the file's own record layout (inside the magic, the header, a
schema, a chunk, a chunk's CRC and size fields, between chunks, before and inside the
summary, the footer's magic, a record's opcode), on a 10 min log written by `leveler sim`.
What each command must do follows from what is readable: a log the writer finished and
whose records all read is used silently; an incomplete one with enough samples is used
with the note (replay and diagnose refuse one with a gap in the middle); one with too few
gets an error saying that the log is incomplete, where and why.

Every case runs through `leveler.cli.main.main` in-process (a traceback would be an exception
out of it); one case of each kind also runs as a real `leveler` process, and all of them do
under `-m slow`.
"""

from __future__ import annotations

import struct
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import pytest
from mcap.opcode import Opcode
from mcap.writer import Writer

from leveler.cli.main import main
from leveler.log.reader import SAMPLE_TOPIC, LogError, read_log

REPO = Path(__file__).resolve().parents[1]
COMMANDS = ("replay", "diagnose", "asd")
MIN_SAMPLES = {"replay": 1000, "diagnose": 1000, "asd": 16}
_MAGIC = 8
_RECORD = struct.Struct("<BQ")


def layout(raw: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, total length) of each top-level record."""
    out, pos = [], _MAGIC
    while pos + _RECORD.size <= len(raw) - _MAGIC:
        opcode, length = _RECORD.unpack_from(raw, pos)
        out.append((pos, opcode, _RECORD.size + length))
        pos += _RECORD.size + length
    return out


def flip(raw: bytes, at: int, bit: int = 3) -> bytes:
    b = bytearray(raw)
    b[at] ^= 1 << bit
    return bytes(b)


def put(raw: bytes, at: int, new: bytes) -> bytes:
    return raw[:at] + new + raw[at + len(new):]


def not_our_messages(path: Path) -> None:
    """A well-formed MCAP (checksums fine) whose sample messages lack leveler's fields."""
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start()
        channel = w.register_channel(SAMPLE_TOPIC, "json", 0)
        for i in range(2000):
            w.add_message(channel, i, b'{"t_s": %d, "reading": 1.0}' % i, i, i)
        w.finish()


def variants(raw: bytes) -> dict[str, bytes]:
    rec = layout(raw)
    chunks = [(pos, n) for pos, op, n in rec if op == Opcode.CHUNK]
    schema = next(pos for pos, op, _ in rec if op == Opcode.SCHEMA)
    data_end = next(pos for pos, op, _ in rec if op == Opcode.DATA_END)
    footer = next(pos for pos, op, _ in rec if op == Opcode.FOOTER)
    assert len(chunks) >= 3, "the log should have several chunks to damage"
    (c0, n0), (c1, n1), (c2, n2) = chunks[:3]
    size_field = _RECORD.size + 16  # a chunk's body: start and end time, then its sizes
    return {
        "empty": b"",
        "cut inside the magic": raw[:5],
        "magic only": raw[:_MAGIC],
        "cut inside the header": raw[: _MAGIC + 12],
        "cut inside a schema": raw[: schema + 20],
        "cut inside the first chunk": raw[: c0 + n0 // 2],
        "cut after the first chunk": raw[: c0 + n0],
        "cut inside the third chunk": raw[: c2 + n2 // 3],
        "cut before the summary": raw[:data_end],
        "cut inside the summary": raw[: (data_end + footer) // 2],
        "cut inside the closing magic": raw[:-3],
        "bit flip in the first chunk": flip(raw, c0 + n0 // 2),
        "bit flip in the second chunk": flip(raw, c1 + n1 // 2),
        "bit flip in a chunk CRC": flip(raw, c1 + size_field + 8, 0),
        "chunk size beyond 2^63": put(raw, c1 + size_field, struct.pack("<Q", 2**63 + 5)),
        "chunk length beyond the file": put(raw, c1 + 1, struct.pack("<Q", 2**62)),
        "bit flip in a record opcode": flip(raw, c1, 7),
        "zeros over the start": put(raw, 0, bytes(4096)),
        "zeros inside the second chunk": put(raw, c1 + n1 // 3, bytes(n1 // 3)),
        "zeros over the tail": put(raw, len(raw) // 2, bytes(len(raw) - len(raw) // 2)),
        "all zeros": bytes(len(raw)),
        "text": b"this is not a log\n",
        "a config file": (REPO / "config" / "sim.toml").read_bytes(),
        "random bytes": bytes((i * 7919 + 13) % 251 for i in range(50_000)),
    }


@pytest.fixture(scope="module")
def damaged(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Each damaged file by name, next to a real log, the special cases and missing."""
    work = tmp_path_factory.mktemp("corrupt")
    good = work / "good.mcap"
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "sim", "--config",
                           str(REPO / "config" / "sim.toml"), "--duration", "10min", "--out",
                           str(good)], capture_output=True, text=True, timeout=120, cwd=work)
    assert proc.returncode == 0, proc.stderr
    out = {}
    for n, (name, data) in enumerate(variants(good.read_bytes()).items()):
        path = work / f"v{n:02d}.mcap"
        path.write_bytes(data)
        out[name] = path
    out["not leveler's messages"] = work / "foreign.mcap"
    not_our_messages(out["not leveler's messages"])
    out["a directory"] = work / "dir.mcap"
    out["a directory"].mkdir()
    out["missing"] = work / "missing.mcap"
    out["intact"] = good
    assert set(out) == set(NAMES)
    return out


NAMES = ["empty", "cut inside the magic", "magic only", "cut inside the header",
         "cut inside a schema", "cut inside the first chunk", "cut after the first chunk",
         "cut inside the third chunk", "cut before the summary", "cut inside the summary",
         "cut inside the closing magic", "bit flip in the first chunk",
         "bit flip in the second chunk", "bit flip in a chunk CRC", "chunk size beyond 2^63",
         "chunk length beyond the file", "bit flip in a record opcode", "zeros over the start",
         "zeros inside the second chunk", "zeros over the tail", "all zeros", "text",
         "a config file", "random bytes", "not leveler's messages", "a directory", "missing",
         "intact"]
# one of each kind of damage, also run as a real process in the default suite
AS_PROCESS = {"cut inside the header", "cut after the first chunk", "chunk size beyond 2^63",
              "text"}


def check(command: str, path: Path, code: int, err: str) -> str:
    """The exit code and stderr of one run against what the reader can read of `path`;
    returns the outcome (refused, partial, whole) for the coverage check."""
    assert "Traceback" not in err, err
    lines = err.splitlines()
    error = f"leveler {command}: error: "
    try:
        log = read_log(path)
    except LogError as exc:  # not a log at all: the reader's error, which names the file
        assert code == 2 and lines == [error + str(exc)], err
        assert str(exc).startswith(f"{path}: "), err
        return "refused"
    n = len(log.samples["t_s"])
    incomplete = "" if log.complete else f" (the log is incomplete: {log.stop_reason})"
    if n < MIN_SAMPLES[command]:
        assert code == 2 and len(lines) == 1, err
        assert lines[0].startswith(f"{error}{path}: ") and "at least" in lines[0], err
        assert lines[0].endswith(incomplete), err
        return "refused"
    seq = log.samples["seq"]
    if command != "asd" and (seq[1:] - seq[:-1] != 1).any():  # a chunk lost mid-file
        assert code == 2 and lines == [f"{error}{path}: samples missing after seq "
                                       f"{seq[(seq[1:] - seq[:-1] != 1).argmax()]} (replay "
                                       "needs a contiguous log)"], err
        return "refused"
    assert code == 0, err
    if log.complete:
        assert err == "", err
        return "whole"
    assert len(lines) == 1, err
    assert lines[0].startswith(f"leveler {command}: note: {path} is incomplete "
                               f"({log.stop_reason}); used its {n} readable samples."), err
    assert f"`leveler recover {path} --out " in lines[0], err
    return "partial"


def run_in_process(command: str, path: Path, tmp: Path,
                   capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    args = [command, str(path)]
    if command == "diagnose":
        args += ["--model-out", str(tmp / "fitted.toml")]
    code = main(args)
    return code, capsys.readouterr().err


def run_as_process(command: str, path: Path, tmp: Path) -> tuple[int, str]:
    args = [sys.executable, "-m", "leveler.cli", command, str(path)]
    if command == "diagnose":
        args += ["--model-out", str(tmp / f"fitted-{path.stem}.toml")]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120, cwd=tmp)
    return proc.returncode, proc.stderr


OUTCOMES: dict[tuple[str, str], str] = {}


@pytest.mark.parametrize("name", NAMES)
def test_commands_on_damaged_logs(name: str, damaged: dict[str, Path], tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    for command in COMMANDS:
        code, err = run_in_process(command, damaged[name], tmp_path, capsys)
        OUTCOMES[name, command] = check(command, damaged[name], code, err)


def test_the_damage_covers_every_outcome(damaged: dict[str, Path], tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """Not a vacuous pass: refusals, partial use with the note, and whole logs all occur,
    and the cases meant to be usable are."""
    for name in NAMES:
        for command in COMMANDS:
            if (name, command) not in OUTCOMES:  # run alone (-k): fill in
                code, err = run_in_process(command, damaged[name], tmp_path, capsys)
                OUTCOMES[name, command] = check(command, damaged[name], code, err)
    for command in COMMANDS:
        assert OUTCOMES["intact", command] == "whole"
        for name in ("cut after the first chunk", "cut before the summary",
                     "cut inside the closing magic", "bit flip in the second chunk",
                     "chunk size beyond 2^63"):
            assert OUTCOMES[name, command] == "partial", (name, command)
        for name in ("magic only", "cut inside the first chunk", "bit flip in the first chunk",
                     "text", "all zeros", "not leveler's messages", "missing"):
            assert OUTCOMES[name, command] == "refused", (name, command)
    # a chunk skipped mid-file (its opcode damaged): the summary's count gives it away;
    # replay and diagnose need contiguous samples, asd uses what there is and says so
    assert [OUTCOMES["bit flip in a record opcode", c] for c in COMMANDS] == [
        "refused", "refused", "partial"]


def _process_params() -> list[object]:
    return [pytest.param(name, marks=() if name in AS_PROCESS else pytest.mark.slow)
            for name in NAMES]


@pytest.mark.parametrize("name", _process_params())
def test_commands_as_processes(name: str, damaged: dict[str, Path], tmp_path: Path) -> None:
    path = damaged[name]
    with ThreadPoolExecutor(max_workers=len(COMMANDS)) as pool:
        results = list(pool.map(partial(run_as_process, path=path, tmp=tmp_path), COMMANDS))
    for command, (code, err) in zip(COMMANDS, results, strict=True):
        check(command, path, code, err)


@pytest.mark.parametrize("name", ["cut after the first chunk", "cut inside the third chunk",
                                  "bit flip in the second chunk", "cut before the summary"])
def test_recover_makes_the_suggested_complete_copy(name: str, damaged: dict[str, Path],
                                                   tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """What the note tells people to run works, and the copy is then used without a note."""
    fixed = tmp_path / "fixed.mcap"
    assert main(["recover", str(damaged[name]), "--out", str(fixed)]) == 0
    before, after = read_log(damaged[name]), read_log(fixed)
    assert after.complete and len(after.samples["t_s"]) == len(before.samples["t_s"])
    capsys.readouterr()
    assert main(["asd", str(fixed)]) == 0
    assert capsys.readouterr().err == ""
