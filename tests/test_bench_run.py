"""`make bench`'s driver: one table, results.json, and exit 0 whatever a section does."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"

GOOD = '''
SECTION = "fake good"
from common import row
def run(quick):
    return [row(SECTION, "baseline thing", 100.0, "ops/s"),
            row(SECTION, "leveler thing", 250.0, "ops/s", baseline="baseline thing",
                ratio=2.5, goal=">= 2x", met=True, note="quick" if quick else "full"),
            row(SECTION, "slow thing", 3.0, "s", goal="<= 1 s", met=False)]
'''
RAISES = '''
SECTION = "fake raises"
def run(quick):
    raise RuntimeError("the plant fell over")
'''
BROKEN_IMPORT = '''
import a_dependency_nobody_has_xyz
def run(quick):
    return []
'''
MALFORMED = '''
def run(quick):
    return [{"what": "no other keys"}]
'''


@pytest.fixture
def bench(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[ModuleType]:
    for name, text in (("fake_good", GOOD), ("fake_raises", RAISES),
                       ("fake_broken_import", BROKEN_IMPORT), ("fake_malformed", MALFORMED)):
        (tmp_path / f"{name}.py").write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.syspath_prepend(str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_run", BENCH / "run.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    yield mod
    for name in ("common", "fake_good", "fake_raises", "fake_broken_import", "fake_malformed"):
        sys.modules.pop(name, None)


def test_sections_report_rather_than_crash(bench: ModuleType) -> None:
    status, rows = bench.run_section("fake_good", True)
    assert status == "ok" and rows[1]["note"] == "quick" and rows[1]["ratio"] == 2.5

    status, rows = bench.run_section("no_such_section_xyz", True)
    assert status == "not available"
    assert rows[0]["section"] == "no_such_section_xyz" and rows[0]["what"] == "not available"

    status, rows = bench.run_section("fake_raises", False)
    assert status == "error" and rows[0]["section"] == "fake raises"
    assert "RuntimeError: the plant fell over" in rows[0]["note"]

    # A section that is there but cannot import is an error, not "not available".
    status, rows = bench.run_section("fake_broken_import", False)
    assert status == "error" and "a_dependency_nobody_has_xyz" in rows[0]["note"]

    status, rows = bench.run_section("fake_malformed", False)
    assert status == "error" and "malformed row" in rows[0]["note"]


def test_main_prints_one_table_writes_json_and_exits_0(
        bench: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(bench, "SECTIONS", ("fake_good", "fake_raises", "no_such_section_xyz"))
    out = tmp_path / "results.json"
    assert bench.main(["--quick", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.count("what ") == 1  # one table header
    assert "[fake good]" in text and "[fake raises]" in text
    good = next(line for line in text.splitlines() if line.startswith("leveler thing"))
    assert "2.5x" in good and ">= 2x" in good and good.rstrip().endswith("yes")
    slow = next(line for line in text.splitlines() if line.startswith("slow thing"))
    assert slow.rstrip().endswith("NO")
    assert "goals: 1 met, 1 missed" in text

    result = json.loads(out.read_text())  # strict JSON: NaN became null
    assert result["quick"] is True
    assert set(result["machine"]) >= {"cpu_count", "python", "kernel"}
    assert result["sections"]["fake_raises"]["status"] == "error"
    assert result["sections"]["no_such_section_xyz"]["status"] == "not available"
    assert all(s["wall_s"] >= 0 for s in result["sections"].values())
    errors = [r for r in result["rows"] if r["what"] == "error"]
    assert len(errors) == 1 and errors[0]["value"] is None
    assert {r["what"] for r in result["rows"]} >= {"baseline thing", "not available"}


def test_only_and_values(bench: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bench, "SECTIONS", ("fake_good", "fake_raises"))
    with pytest.raises(SystemExit):
        bench.main(["--only", "nonsense"])
    assert bench.main(["--only", "fake_good"]) == 0  # no --out: writes nothing
    assert bench._value(math.nan) == "—" and bench._value(261073.5) == "261,074"
    assert bench._value(0.6384) == "0.638" and bench._ratio(None) == "—"
