"""The open log: a log still being written reads as a stream up to its last complete chunk,
and says so (not "cut short, recover it"); the events also go out as foxglove.Log, the
schema Foxglove's Log panel shows."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from mcap.reader import make_reader

from leveler.log.reader import FOXGLOVE_LOG_TOPIC, partial_note, read_log
from leveler.log.writer import LogWriter
from leveler.records import Event, Sample

T0_NS = 1_700_000_000_123_456_789


def sample(i: int) -> Sample:
    return Sample(seq=i, t_s=i * 0.01, raw_counts=i, sensor_m=1e-9 * i, status=0,
                  setpoint_m=0.0, error_m=0.0, p_v=0.0, i_v=70.0, d_v=0.0, command_v=70.0,
                  applied_v=70.0, saturated=False, state="engaged")


def test_a_log_being_written_reads_as_a_stream_and_says_so(tmp_path: Path) -> None:
    path = tmp_path / "live.mcap"
    log = LogWriter(path, chunk_interval_s=0.05)
    try:
        for i in range(300):
            log.sample(sample(i), T0_NS + i * 10_000_000)
        assert log.wait_drained(timeout=10)
        time.sleep(0.2)  # a chunk boundary passes: what was written is in the file
        live = read_log(path)
        assert live.live and not live.complete
        assert len(live.samples["seq"]) == 300
        assert "still being written" in partial_note(path, live.stop_reason, 300, live.live)
        # the same bytes copied elsewhere are no longer held: a log a crash cut short
        cut = tmp_path / "cut.mcap"
        shutil.copyfile(path, cut)
        copy = read_log(cut)
        assert not copy.live and not copy.complete
        assert "leveler recover" in partial_note(cut, copy.stop_reason, 300, copy.live)
    finally:
        log.close()
    done = read_log(path)
    assert done.complete and not done.live


def test_events_are_also_foxglove_log_messages(tmp_path: Path) -> None:
    path = tmp_path / "events.mcap"
    with LogWriter(path) as log:
        log.sample(sample(0), T0_NS)
        log.event(Event(0.0, "tune", "operator", {"ki_v_per_m_s": 7e5}), T0_NS + 1)
        log.event(Event(0.5, "state", "sensor lost", {"old": "engaged", "new": "fault"}),
                  T0_NS + 500_000_000)
        log.event(Event(0.6, "bad_reading", "sensor reading NaN; voltage held", {}),
                  T0_NS + 600_000_000)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        (channel,) = [c for c in summary.channels.values() if c.topic == FOXGLOVE_LOG_TOPIC]
        schema = summary.schemas[channel.schema_id]
        assert schema.name == "foxglove.Log" and schema.encoding == "jsonschema"
        props = json.loads(schema.data)["properties"]
        messages = [(m.log_time, json.loads(m.data))
                    for _, _, m in reader.iter_messages(topics=[FOXGLOVE_LOG_TOPIC])]
    assert [m["level"] for _, m in messages] == [2, 4, 3]  # INFO, ERROR, WARNING
    for log_time, m in messages:
        assert set(m) == set(props)
        assert m["timestamp"]["sec"] * 1_000_000_000 + m["timestamp"]["nsec"] == log_time
        assert m["name"] == "leveler"
    assert messages[1][1]["message"] == "state: sensor lost"
    assert len(read_log(path).events) == 3  # the leveler events themselves unchanged


def test_the_running_daemons_log_opens_in_asd_and_replay(start_daemon) -> None:  # type: ignore[no-untyped-def]
    d = start_daemon(rate_hz=100.0)
    d.wait_status_lines(1)
    (log,) = d.logs.glob("*.mcap")
    deadline = time.monotonic() + 60
    while len(read_log(log).samples["seq"]) < 1100:  # replay needs 1000
        assert time.monotonic() < deadline, "the daemon's log did not grow"
        time.sleep(1.0)
    for args in (["asd", str(log), "--channel", "sensor_m"], ["replay", str(log)]):
        proc = subprocess.run([sys.executable, "-m", "leveler.cli", *args],
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
        assert "still being written" in proc.stderr, proc.stderr
        assert "recover" not in proc.stderr
    d.stop()
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "asd", str(log),
                           "--channel", "sensor_m"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def test_the_foxglove_layout_names_only_what_the_log_has() -> None:
    """config/foxglove-layout.json: every panel placed, every path a field of a topic the
    writer declares, the Log panel on the foxglove.Log topic."""
    from conftest import REPO

    from leveler.live.foxglove import ASD_SCHEMA, ASD_TOPIC
    from leveler.log import writer

    layout = json.loads((REPO / "config" / "foxglove-layout.json").read_text())
    fields = {"/leveler/sample": writer._SAMPLE_FIELDS, "/leveler/truth": writer._TRUTH_FIELDS,
              ASD_TOPIC: json.loads(ASD_SCHEMA)["properties"]}

    def placed(node: object) -> list[str]:
        return [node] if isinstance(node, str) else [
            p for k in ("first", "second") for p in placed(node[k])]  # type: ignore[index]

    assert sorted(placed(layout["layout"])) == sorted(layout["configById"])
    kinds = {panel.split("!")[0] for panel in layout["configById"]}
    assert {"Plot", "StateTransitions", "RosOut"} <= kinds
    for panel, config in layout["configById"].items():
        if panel.startswith("RosOut"):
            assert config["topicToRender"] == FOXGLOVE_LOG_TOPIC
            continue
        for path in [*config["paths"], *([config["xAxisPath"]] if "xAxisPath" in config else [])]:
            topic, _, field = path["value"].removesuffix("[:]").partition(".")
            assert field in fields[topic], f"{panel}: {path['value']} is in no schema"
