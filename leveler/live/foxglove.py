"""The daemon's live view: the log's topics over Foxglove's WebSocket protocol (foxglove-sdk).

A sink like the log writer: the loop thread only appends to a bounded deque (no lock, no
I/O, no encoding); a background thread drains it, publishes the newest sample and truth at
most `rate_hz` times a second, every event (also as foxglove.Log), and every few seconds the
running ASD of the reading. The SDK's server keeps a bounded queue per client and drops a
slow client's oldest messages, so a client that never reads costs bounded memory.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from leveler.live.config import LiveConfig, parse_address
from leveler.log.reader import (
    ENVIRONMENT_TOPIC,
    EVENT_TOPIC,
    FOXGLOVE_LOG_TOPIC,
    SAMPLE_TOPIC,
    TRUTH_TOPIC,
)
from leveler.log.writer import SCHEMAS, encode, encode_event, foxglove_log
from leveler.records import Environment, Event, Sample, Truth
from leveler.rt import background_thread, on_normal_thread
from leveler.typed_config import ConfigError

ASD_TOPIC = "/leveler/live_asd"
ASD_SCHEMA = json.dumps({
    "title": "leveler.LiveAsd",
    "type": "object",
    "properties": {
        "t_s": {"type": "number", "description": "loop time of the newest sample used [s]"},
        "span_s": {"type": "number", "description": "length of the record analysed [s]"},
        "freq_hz": {"type": "array", "items": {"type": "number"},
                    "description": "log-spaced frequencies [Hz]"},
        "asd_m_rthz": {"type": "array", "items": {"type": "number"},
                       "description": "ASD of the sensor reading (LPSD) [m/sqrt(Hz)]"},
        "log10_freq_hz": {"type": "array", "items": {"type": "number"},
                          "description": "log10 of freq_hz, for a log axis in a Plot panel"},
        "log10_asd_m_rthz": {"type": "array", "items": {"type": "number"},
                             "description": "log10 of asd_m_rthz"},
    },
}).encode()
_MIN_ASD_SAMPLES = 256
_MAX_ASD_SAMPLES = 1 << 20  # 8 MiB of history at most, whatever the rate and span


class FoxgloveStream:
    """Serve the running loop on `cfg.foxglove`; `close()` stops the thread and the server."""

    def __init__(self, cfg: LiveConfig, loop_rate_hz: float) -> None:
        try:
            import foxglove
        except ImportError:
            raise ConfigError("[live] foxglove is set but the foxglove-sdk package is not "
                              "installed: install leveler's `live` extra (docs/install.md), "
                              "or remove [live] foxglove") from None
        self.cfg = cfg
        host, port = parse_address(cfg.foxglove)
        self._ctx = foxglove.Context()
        try:
            # its network threads are started here, and inherit this thread's policy
            self.server = on_normal_thread(lambda: foxglove.start_server(
                name="leveler", host=host, port=port, context=self._ctx))
        except RuntimeError as exc:  # the SDK's error for a taken or forbidden address
            raise ConfigError(f"[live] foxglove = {cfg.foxglove!r}: cannot serve: {exc}"
                              ) from None
        self.url = f"ws://{host}:{self.server.port}"
        channels: dict[str, Any] = {}
        for topic in (SAMPLE_TOPIC, TRUTH_TOPIC, ENVIRONMENT_TOPIC, EVENT_TOPIC,
                      FOXGLOVE_LOG_TOPIC):
            name, schema = SCHEMAS[topic]
            channels[topic] = self._channel(foxglove, topic, name, schema)
        channels[ASD_TOPIC] = self._channel(foxglove, ASD_TOPIC, "leveler.LiveAsd", ASD_SCHEMA)
        self._channels = channels
        self._fs = loop_rate_hz
        # The loop's hand-off: a few seconds at the loop's rate; if the thread ever falls that
        # far behind, the oldest records go (the log has them all).
        self._queue: deque[tuple[str, Any, int]] = deque(
            maxlen=max(int(4 * loop_rate_hz), 64))
        n = min(max(int(cfg.asd_span_s * loop_rate_hz), _MIN_ASD_SAMPLES), _MAX_ASD_SAMPLES)
        self._ring = np.full(n, np.nan)
        self._filled = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foxglove live", daemon=True)
        self._thread.start()

    def _channel(self, foxglove: Any, topic: str, name: str, schema: bytes) -> Any:
        return foxglove.Channel(topic, message_encoding="json", context=self._ctx,
                                schema=foxglove.Schema(name=name, encoding="jsonschema",
                                                       data=schema))

    # -- the loop thread's side: one append each --------------------------------------

    def sample(self, s: Sample, log_time_ns: int) -> None:
        self._queue.append((SAMPLE_TOPIC, s, log_time_ns))

    def truth(self, t: Truth, log_time_ns: int) -> None:
        self._queue.append((TRUTH_TOPIC, t, log_time_ns))

    def environment(self, e: Environment, log_time_ns: int) -> None:
        self._queue.append((ENVIRONMENT_TOPIC, e, log_time_ns))

    def event(self, e: Event, log_time_ns: int) -> None:
        self._queue.append((EVENT_TOPIC, e, log_time_ns))

    # -- the publishing thread --------------------------------------------------------

    def _run(self) -> None:
        background_thread()
        period = 1.0 / self.cfg.rate_hz
        next_asd = time.monotonic() + self.cfg.asd_interval_s
        while not self._stop.wait(period):
            newest: dict[str, tuple[Any, int]] = {}
            while self._queue:
                topic, rec, log_time = self._queue.popleft()
                if topic == EVENT_TOPIC:
                    self._channels[EVENT_TOPIC].log(encode_event(rec), log_time=log_time)
                    self._channels[FOXGLOVE_LOG_TOPIC].log(foxglove_log(rec, log_time),
                                                           log_time=log_time)
                    continue
                newest[topic] = (rec, log_time)
                if topic == SAMPLE_TOPIC:
                    self._ring[self._filled % len(self._ring)] = rec.sensor_m
                    self._filled += 1
            for topic, (rec, log_time) in newest.items():
                self._channels[topic].log(encode(rec), log_time=log_time)
            if time.monotonic() >= next_asd and SAMPLE_TOPIC in newest:
                next_asd = time.monotonic() + self.cfg.asd_interval_s
                message = self.running_asd(newest[SAMPLE_TOPIC][0].t_s)
                if message is not None:
                    self._channels[ASD_TOPIC].log(message, log_time=newest[SAMPLE_TOPIC][1])

    def running_asd(self, t_s: float) -> dict[str, Any] | None:
        """The LPSD of the reading over the history held since its last non-finite value;
        None while that is too short."""
        from leveler.analysis.spectral import lpsd

        n = min(self._filled, len(self._ring))
        start = self._filled % len(self._ring) if self._filled > len(self._ring) else 0
        x = np.roll(self._ring, -start)[:n]
        bad = np.flatnonzero(~np.isfinite(x))  # a fault's NaN: the stretch since the last
        if len(bad):
            x = x[bad[-1] + 1 :]
        if len(x) < _MIN_ASD_SAMPLES:
            return None
        spec = lpsd(x, self._fs, n_freqs=60)
        keep = np.isfinite(spec.asd) & (spec.asd > 0)
        f, a = spec.freq_hz[keep], spec.asd[keep]
        return {"t_s": t_s, "span_s": len(x) / self._fs, "freq_hz": f.tolist(),
                "asd_m_rthz": a.tolist(), "log10_freq_hz": np.log10(f).tolist(),
                "log10_asd_m_rthz": np.log10(a).tolist()}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.server.stop()


