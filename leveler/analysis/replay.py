"""Replay: how well the plant model predicts what the sensor really saw (`leveler replay`).

The metrics are those of the residual (measured minus predicted, after the unknown offset
and the thermal lag's start are removed): RMS, RMS and mean ASD in the paper's bands, and
the fraction of the measured variance the model explains. `what_if` asks what other gains
would have done: the controller is rerun against the model, driven by the same
disturbance the log implies (linear superposition: reading = logged reading + the model's
response to the change in actuator voltage).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from leveler.analysis.diagnose import BANDS_HZ, gap, residual, warmup_samples
from leveler.analysis.drift import bands, drift, noise_periodogram, terms, verdict
from leveler.analysis.predict import Measured, Predictor
from leveler.analysis.spectral import REPORT_FREQS_HZ, asd_or_none
from leveler.loop.feedforward import FeedforwardFilter
from leveler.loop.pid import PID, ControllerConfig
from leveler.sim.pendulum import PendulumModel


def what_if(meas: Measured, pred: Predictor,
            gains: tuple[float, float, float] | ControllerConfig) -> np.ndarray:
    """The sensor reading the logged run would have shown under `gains` (kp, ki, kd in
    place of the logged controller's), or under a whole controller config (resonant terms
    and a temperature feedforward too: that one fed the log's temperature from its first
    sample). The rest of the controller (filter, slew, limits) is the logged one, not the
    --model file's, which may be another stand's or an older one. ValueError for a
    feedforward on a log without a temperature."""
    p = pred.params
    logged = meas.controller if meas.controller is not None else meas.config.controller
    cfg = gains if isinstance(gains, ControllerConfig) else dataclasses.replace(
        logged, kp_v_per_m=gains[0], ki_v_per_m_s=gains[1], kd_v_s_per_m=gains[2])
    pid = PID(cfg.pid_config())
    ff, temp = cfg.feedforward(), meas.sig.temperature_k
    if ff is not None and temp is None:
        raise ValueError(f"{meas.path}: a temperature feedforward needs the log's temperature, "
                         "and it has none")
    fed = None if ff is None else FeedforwardFilter(ff, math.inf)
    pend = PendulumModel(dataclasses.replace(p.pendulum, model="linear"), meas.dt_s)
    kv = p.piezo.gain_m_per_v / p.platform.support_spacing_m
    arm, dt = p.pendulum.sensor_arm_m, meas.dt_s
    lo, hi = p.piezo.min_v, p.piezo.max_v
    max_dv = p.piezo.slew_v_per_s * dt
    y_log, u_log = meas.y_m.tolist(), meas.u_v.tolist()
    out = np.empty(len(y_log))
    pid.engage(y_log[0], u_log[0])
    u = u_log[0]
    for n, (y0, u0) in enumerate(zip(y_log, u_log, strict=True)):
        y = y0 + arm * pend.theta  # the model's response to the change in voltage so far
        out[n] = y
        v = 0.0 if fed is None else fed.feed(n * dt, float(temp[n]))  # type: ignore[index]
        target = min(max(pid.update(y, dt, v).command_v, lo), hi)
        u += min(max(target - u, -max_dv), max_dv)
        pend.step(kv * (u - u0))
    return out



def against_noise(meas: Measured, pred: Predictor, span: slice,
                  method: str) -> dict[str, Any]:
    """The residual against the model's own noise, band by band, and with the slow drift
    (`leveler.analysis.drift`, by `method`) set aside."""
    params, logged = pred.params, meas.sig.temperature_k is not None
    r = residual(meas, pred, span)
    y = meas.y_m[span] - meas.y_m[span].mean()
    d = drift(r, method, params, logged, meas.dt_s)
    noise = noise_periodogram(params, logged, len(r), meas.dt_s)
    per_band = bands(y, r, d, meas.dt_s, noise, BANDS_HZ)
    yd, rd = y - d, r - d
    return {
        "drift": method,
        "drift_rms_m": float(np.std(d)),
        "variance_explained_less_drift": (1.0 - float(np.var(rd)) / float(np.var(yd))
                                          if np.var(yd) > 0 else None),
        "bands": per_band,
        "verdict": verdict(per_band, terms(params, logged)),
    }


def replay(meas: Measured, gains: tuple[float, float, float] | None = None,
           drift_method: str = "model") -> tuple[dict[str, Any], Predictor, slice]:
    """The metrics of one replay (and the what-if), with the predictor and the analysed
    span for whoever plots or writes it. The pendulum's start is fitted (`Predictor.ringing`),
    so a model that rings for hours does not lay a wrong start over the comparison."""
    pred = Predictor(meas.config.plant, meas, ringing=True)
    skip = warmup_samples(meas, pred)
    span = slice(skip, len(meas.y_m))
    result: dict[str, Any] = {
        "log": meas.path,
        "model": meas.model_source,
        "samples": len(meas.y_m),
        "rate_hz": 1.0 / meas.dt_s,
        "analysed_s": [float(meas.t_s[skip]), float(meas.t_s[-1])],
        "first_t_s": float(meas.t_s[0]),
        "temperature_logged": meas.sig.temperature_k is not None,
        "filled_samples": meas.bad_samples,
        "effects_in_model": [fx.name for fx in pred.effects],
    } | gap(meas, pred, span) | against_noise(meas, pred, span, drift_method)
    if gains is not None:
        fs = 1.0 / meas.dt_s
        y_new = what_if(meas, pred, gains)[span]
        y_old = meas.y_m[span]
        result["what_if"] = {
            "gains": {"kp_v_per_m": gains[0], "ki_v_per_m_s": gains[1],
                      "kd_v_s_per_m": gains[2]},
            "logged_gains": {"kp_v_per_m": meas.gains[0], "ki_v_per_m_s": meas.gains[1],
                             "kd_v_s_per_m": meas.gains[2]},
            "freq_hz": list(REPORT_FREQS_HZ),
            "measured_asd_m_rthz": asd_or_none(y_old, fs),
            "predicted_asd_m_rthz": asd_or_none(y_new, fs),
            "predicted_rms_m": float(np.std(y_new)),
            "measured_rms_m": float(np.std(y_old)),
        }
    return result, pred, span


def write_replay_log(path: str | Path, meas: Measured, pred: Predictor) -> None:
    """Measured, predicted and residual per sample, as an MCAP topic Foxglove can plot."""
    from mcap.writer import CompressionType, Writer

    schema = json.dumps({"title": "leveler.Replay", "type": "object", "properties": {
        "t_s": {"type": "number", "description": "log time [s]"},
        "measured_m": {"type": "number", "description": "logged sensor reading [m]"},
        "predicted_m": {"type": "number", "description": "model prediction [m]"},
        "residual_m": {"type": "number", "description": "measured - predicted [m]"}}})
    y, yp = meas.y_m, pred.base.y_m
    offset = float(np.median(y - yp))
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start("", "leveler replay")
        sid = w.register_schema("leveler.Replay", "jsonschema", schema.encode())
        cid = w.register_channel("/leveler/replay", "json", sid)
        w.add_metadata("leveler", {"log": meas.path, "model": meas.model_source,
                                    "offset_m": repr(offset)})
        for i, (t, a, b) in enumerate(zip(meas.t_s.tolist(), y.tolist(),
                                          (yp + offset).tolist(), strict=True)):
            ns = max(round(t * 1e9), 0)
            w.add_message(cid, ns, b'{"t_s":%r,"measured_m":%r,"predicted_m":%r,'
                          b'"residual_m":%r}' % (t, a, b, a - b), ns, i)
        w.finish()


def plot_replay(path: str | Path, meas: Measured, pred: Predictor, span: slice,
                title: str) -> None:
    """(a) the sensor and the model's replay of it, block-averaged, (b) the ASDs of the
    sensor and of the residual, with the report's band edges marked and named."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from leveler.analysis.plots import block_means
    from leveler.analysis.spectral import lpsd

    fig = Figure(figsize=(9, 7), layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1)
    y = meas.y_m[span]
    r = residual(meas, pred, span)
    # hours from the first sample, as the report counts: an imported log's clock is absolute
    t, (ym, pm) = block_means((meas.t_s[span] - meas.t_s[0]) / 3600, y, y - r)
    top.plot(t, ym * 1e9, lw=0.8, label="measured")
    top.plot(t, pm * 1e9, lw=0.8, label="model")
    top.set_xlabel("time from the first sample [h]")
    top.set_ylabel("sensor reading [nm]")
    top.legend()
    top.set_title(f"(a) sensor, measured and replayed ({(t[1] - t[0]) * 3600:.0f} s averages)",
                  fontsize=10)
    fs = 1.0 / meas.dt_s
    for label, x in (("measured", y - y.mean()), ("residual = measured − model", r)):
        s = lpsd(x, fs)
        bottom.loglog(s.freq_hz, s.asd, lw=1, label=label)
    # the edges inside the spectra's band: one beyond it would stretch the axis, its name
    # run off the edge
    for lo in (lo for lo, _ in BANDS_HZ.values() if s.freq_hz[0] <= lo <= s.freq_hz[-1]):
        bottom.axvline(lo, color="0.5", ls=":", lw=0.8)
        bottom.annotate(f"{lo * 1e3:g} mHz" if lo < 0.1 else f"{lo:g} Hz", (lo, 1),
                        xycoords=("data", "axes fraction"), xytext=(2, -2),
                        textcoords="offset points", va="top", fontsize=8, color="0.3")
    bottom.set_xlabel("frequency [Hz]")
    bottom.set_ylabel("ASD [m/√Hz]")
    bottom.set_title("(b) spectra; dotted: the report's band edges", fontsize=10)
    bottom.grid(True, which="major", alpha=0.4)
    # spectra fall with frequency: upper right, below the band names, is usually empty
    bottom.legend(loc="upper right", bbox_to_anchor=(1, 0.93))
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
