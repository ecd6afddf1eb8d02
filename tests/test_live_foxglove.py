"""The live view: the daemon (a real subprocess) serves its topics over Foxglove's WebSocket
protocol, read here by a real client (the `websockets` package speaking foxglove.sdk.v1):
the log's schemas, decimated samples, events also as foxglove.Log, a running ASD; a client
that never reads costs bounded memory; off by default; a bad address is a config error."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest
import websockets

from leveler.live.foxglove import ASD_TOPIC
from leveler.log.writer import SCHEMAS
from leveler.records import Sample

LIVE = '\n[live]\nfoxglove = "127.0.0.1:0"\nrate_hz = {rate}\nasd_interval_s = 1.0\n' \
       'asd_span_s = 30.0\n'


def live_daemon(start_daemon: Any, *, loop_hz: float = 50.0, rate: float = 20.0) -> Any:
    d = start_daemon(rate_hz=loop_hz, edit=lambda text: text + LIVE.format(rate=rate))
    d.wait_status_lines(1)
    return d


def url(d: Any) -> str:
    proc = d.cli("status", "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)["live"]["foxglove"]


async def advertised(ws: Any) -> dict[int, dict[str, Any]]:
    while True:
        message = json.loads(await asyncio.wait_for(ws.recv(), 10))
        if message["op"] == "advertise":
            return {c["id"]: c for c in message["channels"]}


async def subscribe_all(ws: Any, channels: dict[int, dict[str, Any]]) -> dict[int, str]:
    subs = {i: c["topic"] for i, c in enumerate(channels.values(), start=1)}
    by_topic = {c["topic"]: c["id"] for c in channels.values()}
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
        {"id": i, "channelId": by_topic[t]} for i, t in subs.items()]}))
    return subs


async def collect(address: str, seconds: float, during: Any = None
                  ) -> tuple[dict[int, dict[str, Any]], dict[str, list[tuple[int, dict]]]]:
    """Every message per topic for `seconds` after subscribing to all; `during()` is
    called (in a thread) once subscribed."""
    async with websockets.connect(address, subprotocols=["foxglove.sdk.v1"]) as ws:
        channels = await advertised(ws)
        subs = await subscribe_all(ws, channels)
        if during is not None:
            asyncio.get_running_loop().run_in_executor(None, during)
        got: dict[str, list[tuple[int, dict]]] = {t: [] for t in subs.values()}
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            try:
                frame = await asyncio.wait_for(ws.recv(), left)
            except TimeoutError:
                break
            if isinstance(frame, bytes):
                opcode, sub, log_time = struct.unpack_from("<BIQ", frame)
                assert opcode == 1  # message data
                got[subs[sub]].append((log_time, json.loads(frame[13:])))
        return channels, got


def test_a_real_client_sees_the_logs_topics_events_and_a_running_asd(start_daemon: Any
                                                                      ) -> None:
    d = live_daemon(start_daemon)
    address = url(d)
    assert address.startswith("ws://127.0.0.1:")

    def tune() -> None:
        time.sleep(1.0)
        assert d.cli("tune", "--ki", "2.1e7").returncode == 0

    channels, got = asyncio.run(collect(address, 8.0, during=tune))
    by_topic = {c["topic"]: c for c in channels.values()}
    for topic, (name, schema) in SCHEMAS.items():
        if topic in ("/leveler/environment", "/leveler/thrust_stand"):
            continue  # what an imported log carries, not the daemon
        assert by_topic[topic]["schemaName"] == name
        assert json.loads(by_topic[topic]["schema"]) == json.loads(schema)
        assert by_topic[topic]["encoding"] == "json"
    samples = [m for _, m in got["/leveler/sample"]]
    assert samples and set(samples[0]) == set(Sample.__dataclass_fields__)
    # decimated: about 20 a second of the loop's 50 (8 s, less the subscription's start)
    assert 60 <= len(samples) <= 8 * 25, len(samples)
    assert samples == sorted(samples, key=lambda s: s["seq"])
    assert got["/leveler/truth"]
    tunes = [m for _, m in got["/leveler/event"] if m["kind"] == "tune"]
    assert tunes and tunes[0]["detail"]["ki_v_per_m_s"] == [2.2e7, 2.1e7]  # (old, new)
    logs = [(t, m) for t, m in got["/leveler/log"] if m["message"].startswith("tune:")]
    assert logs and logs[0][1]["level"] == 2  # INFO
    t, m = logs[0]
    assert m["timestamp"]["sec"] * 1_000_000_000 + m["timestamp"]["nsec"] == t
    asd = [m for _, m in got[ASD_TOPIC]]
    assert asd, "no running ASD within 8 s (needs 256 samples: 5.1 s at 50 Hz)"
    f, a = asd[-1]["freq_hz"], asd[-1]["asd_m_rthz"]
    assert len(f) == len(a) >= 20 and f == sorted(f) and all(x > 0 for x in a)
    assert f[-1] < 25.0  # below the loop's Nyquist frequency
    d.stop()


@pytest.mark.slow  # 16 s of a stalled client (make test-slow); the other tests here cover the view
def test_a_client_that_never_reads_costs_bounded_memory(start_daemon: Any) -> None:
    d = live_daemon(start_daemon, loop_hz=1000.0, rate=1000.0)
    address = url(d)

    def rss_kib() -> int:
        status = Path(f"/proc/{d.proc.pid}/status").read_text()
        return int(next(line.split()[1] for line in status.splitlines()
                        if line.startswith("VmRSS:")))

    async def stall() -> list[int]:
        async with websockets.connect(address, subprotocols=["foxglove.sdk.v1"],
                                      max_queue=1) as ws:
            await subscribe_all(ws, await advertised(ws))
            rss = []
            for _ in range(4):  # buffers fill first: ours, the kernel's, the server's queue
                await asyncio.sleep(4)
                rss.append(rss_kib())
            return rss

    # unread, every 4 s: 4000 samples and 4000 truths at 1 kHz, about 3 MB of JSON, so a
    # server that queued them all would grow some 6 MB over the last two intervals (the
    # first is the buffers filling); 4 MiB allowed, for the allocator's own breathing
    rss = asyncio.run(stall())
    print(f"RSS every 4 s with the client asleep: {rss} KiB")
    assert rss[3] - rss[1] < 4096, f"RSS grows: {rss} KiB"
    status = json.loads(d.cli("status", "--json").stdout)
    assert status["state"] == "engaged" and not status["loop"]["stalled"]
    d.stop()


def test_off_by_default(start_daemon: Any) -> None:
    d = start_daemon()
    d.wait_status_lines(1)
    assert json.loads(d.cli("status", "--json").stdout)["live"] == {"foxglove": None,
                                                                    "epics": None}
    d.stop()


@pytest.mark.parametrize(("value", "says"), [
    ('"lab-pc:8765"', "not an IP address"),
    ('"127.0.0.1"', "not HOST:PORT"),
    ('"127.0.0.1:99999"', "not HOST:PORT"),
])
def test_a_bad_address_is_a_config_error_naming_the_key(tmp_path: Path, value: str,
                                                         says: str) -> None:
    from conftest import REPO

    cfg = tmp_path / "bad.toml"
    cfg.write_text((REPO / "config" / "sim.toml").read_text() + f"\n[live]\nfoxglove = {value}\n")
    proc = subprocess.run([sys.executable, "-m", "leveler.cli", "run", "--config", str(cfg)],
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert proc.returncode == 2
    assert "live: foxglove" in proc.stderr and says in proc.stderr and str(cfg) in proc.stderr
    assert not (tmp_path / "logs").exists()  # refused before a log was made


def test_malformed_and_hostile_input_is_rejected_and_reaches_nothing(start_daemon: Any
                                                                     ) -> None:
    """Garbage frames, unknown ops, a client trying to publish on the loop's topics, set
    parameters or call services, and raw bytes that are no WebSocket at all: each client is
    refused or ignored, the loop runs on unchanged, and a good client still gets data."""
    import socket

    d = live_daemon(start_daemon)
    address = url(d)
    before = json.loads(d.cli("status", "--json").stdout)
    hostile: list[str | bytes] = [
        b"\x00\xff" * 100, "not json", json.dumps({"op": "nonsense"}), json.dumps([1, 2]),
        json.dumps({"op": "subscribe", "subscriptions": [{"id": "x", "channelId": -1}]}),
        json.dumps({"op": "advertise", "channels": [{"id": 1, "topic": "/leveler/sample",
                                                     "encoding": "json",
                                                     "schemaName": "leveler.Sample"}]}),
        b"\x01\x01\x00\x00\x00" + json.dumps({"command_v": 150.0}).encode(),
        json.dumps({"op": "setParameters", "parameters": [{"name": "ki_v_per_m_s",
                                                           "value": 1e12}]}),
        json.dumps({"op": "callService", "serviceId": 1, "callId": 1, "encoding": "json",
                    "payload": "{}"}),
    ]

    async def attack() -> None:
        for frame in hostile:
            try:
                async with websockets.connect(address, subprotocols=["foxglove.sdk.v1"]) as ws:
                    await advertised(ws)
                    await ws.send(frame)
                    await asyncio.wait_for(ws.recv(), 1.0)  # an error status, or nothing
            except (TimeoutError, websockets.ConnectionClosed):
                pass

    asyncio.run(attack())
    host, port = address.removeprefix("ws://").split(":")
    with socket.create_connection((host, int(port)), timeout=5) as raw:  # no handshake at all
        raw.sendall(b"\x16\x03\x01\x02\x00" + bytes(range(256)) * 4)
        raw.settimeout(2)
        try:
            raw.recv(1024)
        except OSError:
            pass
    _, got = asyncio.run(collect(address, 2.0))
    assert got["/leveler/sample"], "a good client gets nothing after the attack"
    after = json.loads(d.cli("status", "--json").stdout)
    assert after["state"] == "engaged" and after["controller"] == before["controller"]
    assert after["loop"]["cycles"] > before["loop"]["cycles"] and not after["loop"]["stalled"]
    d.stop()
    (log,) = d.logs.glob("*.mcap")
    from leveler.log.reader import read_log

    events = read_log(log).events
    assert not {e["kind"] for e in events} & {"tune", "procedure", "reload"}  # nothing driven
    states = [e["detail"]["new"] for e in events if e["kind"] == "state"]
    assert states == ["engaged", "idle"], states  # closed at start, opened at stop: no other


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0
                    or shutil.which("chrt") is None,
                    reason="needs root and chrt to run the daemon under SCHED_FIFO")
def test_the_servers_network_threads_run_below_the_loop(tmp_path: Path) -> None:
    """Under SCHED_FIFO, as under the service: the Foxglove server's own (Rust) threads are
    started at normal scheduling, not at the loop's priority they would inherit."""
    from conftest import daemon_config

    sock = Path(tempfile.mkdtemp(prefix="lv", dir="/tmp")) / "c.sock"
    config = daemon_config(tmp_path, sock, rate_hz=20.0,
                           edit=lambda text: text + LIVE.format(rate=20.0))
    proc = subprocess.Popen(["chrt", "-f", "10", sys.executable, "-m", "leveler.cli", "run",
                             "--config", str(config)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 30
        while not sock.exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        policy = {}
        for task in Path(f"/proc/{proc.pid}/task").iterdir():
            name = (task / "comm").read_text().strip()
            policy[f"{name}/{task.name}"] = os.sched_getscheduler(int(task.name))
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    network = {k: v for k, v in policy.items() if k.startswith("tokio")}
    assert network, f"no server threads found: {sorted(policy)}"
    assert set(network.values()) == {os.SCHED_OTHER}, network
    assert os.SCHED_FIFO in policy.values()  # the daemon itself does run real-time
