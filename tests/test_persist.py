"""Writing tuned values back into a commented config file, atomically."""

from __future__ import annotations

from pathlib import Path

import pytest

from leveler.daemon.persist import set_keys, write_atomic
from leveler.settings import load_config
from leveler.typed_config import ConfigError

REPO = Path(__file__).resolve().parents[1]


def test_values_replaced_in_place_comments_kept() -> None:
    text = (REPO / "config" / "sim.toml").read_text()
    out = set_keys(text, "controller", {"d_filter_tau_s": 0.25, "kp_v_per_m": 1000.0})
    assert "d_filter_tau_s = 0.25       # bounds D above" in out
    assert "kp_v_per_m = 1000.0\n" in out
    assert out.count("d_filter_tau_s") == 1
    before, after = text.splitlines(), out.splitlines()
    assert len(before) == len(after)
    assert sum(a != b for a, b in zip(before, after, strict=True)) == 2


def test_missing_key_is_added_to_its_section_not_elsewhere() -> None:
    text = ("[loop]\nrate_hz = 10.0\n\n[controller]\nki_v_per_m_s = 1.0\n\n"
            "[sensor]\nbackend = 'sim'\n")
    out = set_keys(text, "controller", {"kd_v_s_per_m": 2.0})
    assert out.index("kd_v_s_per_m = 2.0") < out.index("[sensor]")
    assert out.index("kd_v_s_per_m = 2.0") > out.index("[controller]")


def test_missing_section_is_appended() -> None:
    out = set_keys("[loop]\nrate_hz = 10.0", "controller", {"ki_v_per_m_s": 3.0})
    assert out.endswith("[controller]\nki_v_per_m_s = 3.0\n")


def test_atomic_write_validates_before_replacing(tmp_path: Path) -> None:
    path = tmp_path / "lab.toml"
    original = (REPO / "config" / "sim.toml").read_text()
    path.write_text(original)
    path.chmod(0o640)
    with pytest.raises(ConfigError):
        write_atomic(path, original.replace("rate_hz = 10.0", "rate_hz = -1.0"), load_config)
    assert path.read_text() == original
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind
    new = set_keys(original, "controller", {"ki_v_per_m_s": 5e5})
    write_atomic(path, new, load_config)
    cfg, _ = load_config(path)
    assert cfg.controller.ki_v_per_m_s == 5e5
    assert path.stat().st_mode & 0o777 == 0o640


def test_atomic_write_gives_the_mode_asked_for_from_the_start(tmp_path: Path) -> None:
    path = tmp_path / "unit.service"
    modes = []
    write_atomic(path, "[Unit]\n", lambda tmp: modes.append(tmp.stat().st_mode & 0o777),
                 mode=0o644)
    assert path.read_text() == "[Unit]\n" and path.stat().st_mode & 0o777 == 0o644
    assert modes == [0o600]  # while it is written nobody else can read a half file
    assert list(tmp_path.iterdir()) == [path]


@pytest.mark.parametrize("form, text", [
    ("dotted keys", "# lab B\ncontroller.kp_v_per_m = 1.0  # P gain\n"
                    "controller.ki_v_per_m_s = 7e5\n\n[loop]\nrate_hz = 10.0\n"),
    ("inline table", "controller = {kp_v_per_m = 1.0, ki_v_per_m_s = 7e5}  # gains\n"
                     "[loop]\nrate_hz = 10.0\n"),
    ("table", "[controller]\n# gains\nkp_v_per_m = 1.0   # P gain\nki_v_per_m_s = 7e5\n"
              "[loop]\nrate_hz = 10.0\n"),
])
def test_every_valid_form_keeps_its_form_and_comments(tmp_path: Path, form: str,
                                                      text: str) -> None:
    """A config with dotted keys once came out with a second [controller] table, failed
    validation and nothing was saved."""
    import tomllib

    out = set_keys(text, "controller", {"ki_v_per_m_s": 5e5, "kd_v_s_per_m": 0.5})
    data = tomllib.loads(out)  # valid TOML, one controller table
    assert data["controller"] == {"kp_v_per_m": 1.0, "ki_v_per_m_s": 5e5, "kd_v_s_per_m": 0.5}
    assert data["loop"] == {"rate_hz": 10.0}
    assert out.count("[controller]") == text.count("[controller]")
    for comment in ("# P gain", "# gains", "# lab B"):
        assert (comment in out) == (comment in text), comment
    if form == "dotted keys":
        assert "controller.ki_v_per_m_s = 500000.0" in out
    if form == "inline table":
        assert out.startswith("controller = {") and "} # gains" in out.replace("}  #", "} #")
    path = tmp_path / "lab.toml"
    path.write_text(text)
    write_atomic(path, out, lambda tmp: tomllib.loads(tmp.read_text()))
    assert path.read_text() == out


def test_a_nested_section_and_removing_a_table() -> None:
    from leveler.daemon.persist import without_table

    out = set_keys("[loop]\nrate_hz = 10.0\n", "plant.pendulum", {"mass_kg": 3.0})
    assert "[plant.pendulum]\nmass_kg = 3.0" in out and "[plant]\n" not in out
    text = "plant.effects.cooler.period_s = 300.0\nplant.x = 1\n[loop]\nrate_hz = 10.0\n"
    kept = without_table(text, "plant.effects")
    assert "effects" not in kept and "plant.x = 1" in kept and "[loop]" in kept


def test_text_that_is_not_toml_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="not valid TOML"):
        set_keys("[controller\nkp = 1\n", "controller", {"kp_v_per_m": 1.0})
