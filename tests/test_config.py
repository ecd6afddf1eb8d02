"""Config errors name the file and the key, and nothing is guessed."""

from __future__ import annotations

from pathlib import Path

import pytest

from leveler.cli.durations import parse_duration
from leveler.settings import Config, config_diff, effective_values, explicit_keys, load_config
from leveler.typed_config import ConfigError

REPO = Path(__file__).resolve().parents[1]


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "lab.toml"
    path.write_text(text)
    return path


def test_shipped_sim_config_loads_and_matches_the_paper() -> None:
    cfg, text = load_config(REPO / "config" / "sim.toml")
    assert isinstance(cfg, Config)
    assert "[controller]" in text
    assert cfg.plant.pendulum.amplification == pytest.approx(9.0, rel=0.01)
    assert cfg.sensor.backend == "sim"


@pytest.mark.parametrize("text", ["", "\n\n", "   \n\t\n", "# the lab's config\n# (cut)\n"])
def test_an_empty_config_is_refused_not_run_on_defaults(tmp_path: Path, text: str) -> None:
    """An emptied or truncated file would otherwise run the simulator on built-in
    defaults, for `run` and for a SIGHUP reload alike (both go through load_config)."""
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(err.value).startswith(f"{path}: is empty: no tables or keys")


def test_one_empty_table_is_a_config_and_takes_the_defaults(tmp_path: Path) -> None:
    cfg, _ = load_config(write(tmp_path, "[loop]\n"))
    assert cfg == Config()


def test_the_simulated_actuators_safe_v_must_be_in_the_piezo_range(tmp_path: Path) -> None:
    """Like [actuator.modbus]/[actuator.serial]: a config error, not a driver traceback."""
    path = write(tmp_path, '[actuator]\nbackend = "sim"\nsafe_v = 200.0\n')
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(err.value) == (f"{path}: actuator.safe_v: 200.0 V is outside the simulated "
                              "piezo's range [plant.piezo] min_v..max_v = [0.0, 150.0] V")
    cfg, _ = load_config(write(tmp_path, "[actuator]\nsafe_v = 20.0\n[plant.piezo]\n"
                               "min_v = 10.0\nref_v = 20.0\n"))
    assert cfg.actuator.safe_v == 20.0


@pytest.mark.parametrize(
    ("base", "values", "needle"),
    [
        ("sim.toml", {"setpoint_m": 1.0}, "setpoint_m 1 m is outside what the sensor reads, "
                                          "(-5e-05, 5e-05) m ([plant.sensor])"),
        ("lab-modbus.toml", {"setpoint_m": -6e-5}, "([sensor.modbus])"),
        ("lab-serial.toml", {"setpoint_m": 5e-5}, "([sensor.serial])"),
        ("lab-nidaq.toml", {"setpoint_m": 1e-4}, "([sensor.nidaq])"),
        ("sim.toml", {"output_max_v": 1e6}, "output_max_v 1e+06 V is outside the actuator's "
                                            "range [0, 150] V ([plant.piezo])"),
        ("lab-modbus.toml", {"output_min_v": -1.0}, "([actuator.modbus])"),
        ("lab-serial.toml", {"output_max_v": 151.0}, "([actuator.serial])"),
        ("lab-nidaq.toml", {"output_min_v": -5.0}, "([actuator.nidaq])"),
        ("sim.toml", {"ki_v_per_m_s": 1e30}, "ki_v_per_m_s 1e+30 is implausible: above 1.5e+15"),
        ("sim.toml", {"kp_v_per_m": 2e14}, "kp_v_per_m 2e+14 is implausible: above 1.5e+14"),
        ("lab-modbus.toml", {"kd_v_s_per_m": 1e20}, "kd_v_s_per_m 1e+20 is implausible"),
    ],
)
def test_tune_values_are_checked_against_the_devices(base: str, values: dict[str, float],
                                                     needle: str) -> None:
    from leveler.settings import check_tune_values

    cfg, _ = load_config(REPO / "config" / base)
    with pytest.raises(ValueError) as err:
        check_tune_values(cfg, values)
    assert needle in str(err.value)
    check_tune_values(cfg, {"setpoint_m": 2e-6, "output_min_v": 10.0, "output_max_v": 140.0,
                            "kp_v_per_m": 1e9, "ki_v_per_m_s": 1e12, "kd_v_s_per_m": 1e9})


def test_an_implausible_gain_in_a_config_file_is_refused_naming_file_and_key(
        tmp_path: Path) -> None:
    text = (REPO / "config" / "sim.toml").read_text()
    assert "ki_v_per_m_s = 2.2e7" in text
    bad = tmp_path / "typo.toml"
    bad.write_text(text.replace("ki_v_per_m_s = 2.2e7", "ki_v_per_m_s = 2.2e70"))
    with pytest.raises(ConfigError, match=rf"{bad}: controller.ki_v_per_m_s 2.2e\+70 is "
                                          "implausible"):
        load_config(bad)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[loop]\nrate_hz = 'fast'\n", "loop.rate_hz: expected a number"),
        ("[loop]\nrate_hz = -10.0\n", "loop.rate_hz: must be > 0"),
        ("[loop]\nrate_hz = nan\n", "loop.rate_hz: must be finite"),
        ("[loop]\nrate_hx = 10.0\n", "loop.rate_hx: unknown key"),
        ("[lop]\nrate_hz = 10.0\n", "lop: unknown key"),
        ("[controller]\nki_v_per_m_s = true\n", "controller.ki_v_per_m_s: expected a number"),
        ("[controller]\noutput_min_v = 200.0\n", "output_min_v (200.0) must be below"),
        ("[sensor]\nbackend = 'serial9'\n", "sensor.backend: expected 'sim'"),
        ("[plant.sensor]\nadc_bits = 16.5\n", "plant.sensor.adc_bits: expected an integer"),
        ("[plant.pendulum]\nmass_kg = 1.0\n", "no stable equilibrium"),
        ("[plant]\npendulum = 3\n", "plant.pendulum: expected a table"),
        ("[loop\nrate_hz = 1\n", "invalid TOML"),
    ],
)
def test_bad_values_name_file_and_key(tmp_path: Path, text: str, needle: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(path) in str(err.value)
    assert needle in str(err.value)


def test_missing_file_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ConfigError, match=r"no such config file$"):
        load_config(tmp_path / "absent.toml")
    # a relative default read outside a checkout says where it looked and what to do
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as err:
        load_config("config/sim.toml")
    assert str(err.value) == (f"config/sim.toml: no such config file in {tmp_path}; "
                              "name one with --config FILE")


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("3600s", 3600.0), ("90m", 5400.0), ("6h", 21600.0), ("1d", 86400.0), ("2.5s", 2.5),
     ("24h", 86400.0), ("10min", 600.0), ("1.5d", 129600.0)],
)
def test_durations(text: str, seconds: float) -> None:
    assert parse_duration(text) == seconds


@pytest.mark.parametrize("text", ["", "h", "-5s", "0s", "6 hours", "1e400s"])
def test_bad_durations(text: str) -> None:
    with pytest.raises(ValueError, match="bad duration"):
        parse_duration(text)


def test_a_bare_number_is_refused_with_the_fix(capsys: pytest.CaptureFixture[str]) -> None:
    """`sim --duration 24` once meant 24 s; the person typing it meant a day."""
    from leveler.cli.main import main

    with pytest.raises(ValueError, match=r"give its unit, e\.g\. 24s, 24m or 24h"):
        parse_duration("24")
    with pytest.raises(SystemExit) as exit_:
        main(["sim", "--duration", "24"])
    assert exit_.value.code == 2
    assert "give its unit, e.g. 24s, 24m or 24h" in capsys.readouterr().err


def _keys(cls: type, prefix: str = "") -> list[str]:
    """Every key of a config section, recursing into tables (optional ones too: effects)."""
    import dataclasses
    import typing

    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        table = [t for t in typing.get_args(hints[f.name]) if dataclasses.is_dataclass(t)]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(default):
            out += _keys(type(default), f"{prefix}{f.name}.")
        elif table:
            out.append(f"{prefix}{f.name}")
            out += _keys(table[0], f"{prefix}{f.name}.")
        else:
            out.append(f"{prefix}{f.name}")
    return out


def test_every_key_is_documented() -> None:
    doc = (REPO / "docs" / "configuration.md").read_text()
    missing = [k for k in _keys(Config)
               if f"`{k.rsplit('.', 1)[-1]}`" not in doc and f"`{k}`" not in doc]
    assert not missing, f"undocumented config keys: {missing}"


def test_a_reload_sees_which_keys_a_file_sets_and_what_changed() -> None:
    """The reload guard's two measures: keys a file sets itself (an array of tables counts
    once) and the effective values that differ (defaults included)."""
    text = ('[loop]\nrate_hz = 10.0\n[controller]\nki_v_per_m_s = 1e5\n'
            '[plant.pendulum]\nmass_kg = 0.2\n'
            '[[sim.faults]]\nkind = "nan"\nat_s = 1.0\nduration_s = 1.0\n')
    assert explicit_keys(text) == {"loop.rate_hz", "controller.ki_v_per_m_s",
                                   "plant.pendulum.mass_kg", "sim.faults"}
    cut = text[:text.index("[plant")]
    assert explicit_keys(text) - explicit_keys(cut) == {"plant.pendulum.mass_kg", "sim.faults"}
    old, new = Config(), load_config(REPO / "config" / "sim.toml")[0]
    diff = config_diff(old, new)
    assert diff["controller.kd_v_s_per_m"] == (0.0, 1.9e6)
    assert "loop.rate_hz" not in diff  # 10 Hz in both: not a change
    assert config_diff(new, new) == {}
    assert set(diff) <= set(effective_values(new))
    assert effective_values(new)["plant.piezo.max_v"] == 150.0
