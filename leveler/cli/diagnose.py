"""`leveler diagnose`: find and fit what the plant model misses; the fitted model, a report."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from leveler.errors import LogError

if TYPE_CHECKING:
    from leveler.analysis.diagnose import Candidate, Diagnosis
    from leveler.analysis.nullcal import NullCalibration
    from leveler.analysis.predict import Measured
    from leveler.cli.progress import Stages
    from leveler.sim.effects import Effect
    from leveler.sim.params import PlantParams



def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "diagnose", help="find, name and fit what the plant model is missing",
        description="Replay the log, look for structure in the residual (spectral lines, "
        "coherence with the actuator and the temperature, a lattice in the readings, "
        "trends), fit each named effect (periodic_disturbance, temperature_coupling, "
        "actuator_delay, actuator_hysteresis, extra_resonance, sensor_gain_error, "
        "sensor_drift, adc_quantization) on the first two thirds of each part of the log (a "
        "modulation with the loop open, the closed loop) and keep it only if it predicts the "
        "held-out last third of each better than its threshold (calibrated on null logs of "
        "the model with --null-runs, else a complexity penalty); repeat while one "
        "does. Writes the updated model (a plain config: `leveler sim --config` and "
        "`leveler replay --model` use it) next to the log as LOG.fitted.toml. Says so, and "
        "writes nothing, when no effect is missing.")
    p.add_argument("log", help="MCAP log written by leveler (or by `leveler import-csv`)")
    p.add_argument("--model", default=None, help="config file whose [plant] is the model "
                   "to test (default: the config stored in the log)")
    p.add_argument("--model-out", default=None,
                   help="where to write the fitted model (default: LOG.fitted.toml)")
    p.add_argument("--report", default=None, metavar="DIR",
                   help="write residual_asd.png, timeseries.png and summary.md here")
    p.add_argument("--max-effects", type=int, default=4,
                   help="stop after this many effects (0: recalibrate and report what "
                   "is left unexplained; default: %(default)s)")
    p.add_argument("--null-runs", type=int, default=0, metavar="N",
                   help="calibrate each family's acceptance threshold on N simulated logs "
                   "of the model with nothing missing (its numbers and noise drawn from "
                   "their tolerances, on this log's schedule), for 1 %% false alarms per "
                   "log; cached per model file and log shape, so later logs like it reuse "
                   "it. About 5-20 s per run and core for a 3 h log at 10 Hz; 50 is a good "
                   "number. 0 (default): use a cached calibration if there is one, else a "
                   "BIC penalty per family")
    p.add_argument("--jobs", type=int, default=None,
                   help="processes for the null runs and for the effect families of "
                   "each round of the search (default: one per core)")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object: effects, gap_before, gap_after, model_out, "
                   "and every candidate tried with its scores")
    p.set_defaults(func=run)


def _toml_value(v: Any) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf")
    return repr(v)


def recalibrated_values(nominal: PlantParams, fitted: PlantParams) -> dict[str, dict[str, float]]:
    """The [plant.*] values recalibration changed, by section."""
    out: dict[str, dict[str, float]] = {}
    for section in ("pendulum", "piezo", "thermal", "cooler"):
        a, b = getattr(nominal, section), getattr(fitted, section)
        changed = {f.name: getattr(b, f.name) for f in dataclasses.fields(b)
                   if getattr(a, f.name) != getattr(b, f.name)}
        if changed:
            out[f"plant.{section}"] = changed
    return out


def model_text(base_text: str, effects: list[Effect], source: str,
               recalibrated: dict[str, dict[str, float]] | None = None) -> str:
    """The base config with the recalibrated values and its [plant.effects.*] tables
    replaced by the fitted ones: a plain config that `leveler sim` and `leveler replay
    --model` read directly."""
    from leveler.daemon.persist import set_keys, without_table

    for section, values in (recalibrated or {}).items():
        base_text = set_keys(base_text, section, values)
    kept = without_table(base_text, "plant.effects").rstrip("\n")
    text = kept + "\n" if kept else ""
    text += (f"\n# Effects fitted by `leveler diagnose` ({source}); "
             "uncertainties in the diagnose report.\n")
    for fx in effects:
        text += f"\n[plant.effects.{fx.name}]  # {fx.describe()}\n"
        for key, value in fx.values().items():
            text += f"{key} = {_toml_value(value)}\n"
    return text


def default_model_path(log: str | Path) -> Path:
    p = Path(log)
    return p.with_name(p.stem + ".fitted.toml")


def _gap_dict(g: dict[str, Any]) -> dict[str, Any]:
    return {"rms_m": g["rms_m"], "band_rms_m": g["band_rms_m"],
            "band_asd_m_rthz": g["band_asd_m_rthz"],
            "variance_explained": g["variance_explained"]}


def headline_band(d: Diagnosis) -> str | None:
    """The band where the model improved most (what a summary line should quote)."""
    from leveler.analysis.diagnose import BANDS_HZ

    best, ratio = None, 1.0
    for band in BANDS_HZ:
        a, b = d.gap_before["band_rms_m"][band], d.gap_after["band_rms_m"][band]
        if a and b and a / b > ratio:
            best, ratio = band, a / b
    return best


def result_json(d: Diagnosis, meas: Measured, model_out: str | None,
                cal: NullCalibration | None = None) -> dict[str, Any]:
    return {
        "log": meas.path,
        "model_in": meas.model_source,
        "effects": [{"name": f.effect.name, "description": f.effect.describe(),
                     "params": f.effect.values(),
                     "uncertainty": f.sigma, "deviance_held_out": f.deviance_test}
                    for f in d.effects],
        "recalibration": None if d.recalibration is None else d.recalibration.as_dict(),
        "recalibration_held": [] if d.recalibration is None else list(d.recalibration.held),
        "gap_before": _gap_dict(d.gap_before),
        "gap_after": _gap_dict(d.gap_after),
        "gap_normalised": d.gap_normalised,
        "model_out": model_out,
        "analysed_s": list(d.span_s),
        "temperature_logged": meas.sig.temperature_k is not None,
        "ambiguous": [{"name": c.name, "params": c.params, "uncertainty": c.sigma,
                       "deviance_held_out": c.deviance_test, "score": c.score}
                      for c in d.ambiguous] or None,
        "unexplained": None if d.leftover is None else d.leftover.as_dict(),
        "unseen": d.unseen,
        "thresholds": thresholds_json(cal),
        "candidates": [{"name": c.name, "round": c.round, "params": c.params,
                        "uncertainty": c.sigma, "deviance_train": c.deviance_train,
                        "deviance_held_out": c.deviance_test, "penalty": c.penalty,
                        "threshold": c.threshold if math.isfinite(c.threshold) else None,
                        "accepted": c.accepted, "note": c.note,
                        "bands_held_out": {b: dataclasses.asdict(v)
                                           for b, v in c.bands.items()} or None}
                       for c in d.candidates],
        "wall_s": d.wall_s,
    }


def thresholds_json(cal: NullCalibration | None) -> dict[str, Any]:
    if cal is None:
        return {"source": "BIC penalty", "runs": 0, "alpha": None, "by_family": None}
    return {"source": "null calibration", "runs": cal.runs, "alpha": cal.alpha,
            "by_family": cal.thresholds, "key": cal.key}


def thresholds_line(cal: NullCalibration | None) -> str:
    if cal is not None:
        return cal.describe()
    return ("acceptance thresholds: a BIC penalty per family, not calibrated on null data "
            "(--null-runs 50 calibrates them for this model and log shape)")


def summary(d: Diagnosis, model_out: str | None, cal: NullCalibration | None = None) -> str:
    lines = []
    if d.recalibration is not None:
        lines.append("recalibrated within the model's stated tolerances:")
        lines += [f"  {line}" for line in d.recalibration.describe()]
    for f in d.effects:
        sig = ", ".join(f"{k} ± {v:.2g}" for k, v in f.sigma.items())
        lines.append(f"missing effect: {f.effect.describe()} ({sig})")
    if d.ambiguous:
        from leveler.analysis.diagnose import AMBIGUITY, AMBIGUITY_REL

        a, b = d.ambiguous
        lines.append(f"ambiguous between {_title(a)} and {_title(b)}: held-out evidence "
                     f"{a.score:.4g} vs {b.score:.4g}, within the margin "
                     f"({AMBIGUITY:g} or {AMBIGUITY_REL:.0%}); neither is added to the model")
    elif not d.effects and not d.candidates:
        lines.append("no effect was searched for; the model is left as it is.")
    elif not d.effects:
        lines.append(_none_found(d))
    if d.candidates:
        lines.append(thresholds_line(cal))
    if d.leftover is not None:
        lines.append(d.leftover.describe())
    if d.unseen:
        from leveler.sim.effects import EFFECTS

        lines.append("what this log cannot show:")
        lines += [f"  {EFFECTS[name].title}: {why}" for name, why in d.unseen.items()]
    if d.effects:
        band = headline_band(d)
        if band:
            a, b = d.gap_before["band_rms_m"][band], d.gap_after["band_rms_m"][band]
            lines.append(f"residual RMS {a * 1e9:.3g} nm -> {b * 1e9:.3g} nm ({a / b:.1f}x) "
                         f"in {band}")
        lines.append(f"residual RMS overall {d.gap_before['rms_m'] * 1e9:.3g} nm -> "
                     f"{d.gap_after['rms_m'] * 1e9:.3g} nm")
        norm = [f"{band} {v['before']:.3g} -> {v['after']:.3g}"
                for band, v in d.gap_normalised.items() if v]
        if norm:
            lines.append("residual power over the noise spectrum, held-out part (1 = noise): "
                         + "; ".join(norm))
    if model_out:
        lines.append(f"model updated: {model_out}")
    return "\n".join(lines)


def _none_found(d: Diagnosis) -> str:
    """Why nothing was named: no candidate beat its threshold held out, or some did and
    a later check stopped each (the best one's reason given: a fit on the held-out part
    alone that disagrees is not "nothing improved the log")."""
    last = max(c.round for c in d.candidates)
    beat = [c for c in d.candidates
            if c.round == last and c.size_ok and c.deviance_test > c.threshold]
    if not beat:
        return ("no missing effect found: no candidate improved the held-out part of the "
                "log beyond its threshold; the model is left as it is.")
    best = max(beat, key=lambda c: c.score)
    why = best.note or "not confirmed"
    some = (f"{len(beat)} candidates improved the held-out part beyond their thresholds, "
            "but none held up; the best," if len(beat) > 1 else
            "1 candidate improved the held-out part beyond its threshold, but did not hold "
            "up:")
    return (f"no missing effect found: {some} {_title(best)} "
            f"(held-out evidence {best.deviance_test:.4g}, threshold {best.threshold:.3g}): "
            f"{why}. The model is left as it is; the residual RMS is "
            f"{d.gap_after['rms_m'] * 1e9:.3g} nm ({d.gap_before['rms_m'] * 1e9:.3g} nm "
            "before the recalibration).")


def _title(c: Candidate) -> str:
    from leveler.sim.effects import EFFECTS

    return EFFECTS[c.name](**c.params).describe()


def ranked_table(d: Diagnosis, rows: int = 8) -> str:
    """Markdown: the last round's candidates by held-out evidence, best first."""
    last = max((c.round for c in d.candidates), default=0)
    cands = sorted((c for c in d.candidates if c.round == last and c.penalty > 0),
                   key=lambda c: -c.score)[:rows]
    if not cands:
        return "- none: no family had a guess to fit"
    out = ["| rank | candidate | held-out 2 ln L gain | threshold | uncertainties | verdict |",
           "|---|---|---|---|---|---|"]
    for i, c in enumerate(cands, 1):
        sig = ", ".join(f"{k} ± {v:.2g}" for k, v in c.sigma.items())
        verdict = "accepted" if c.accepted else (c.note or (
            "below its threshold" if c.score <= 0 else "not the best"))
        out.append(f"| {i} | {_title(c)} | {c.deviance_test:.4g} | {c.threshold:.3g} | "
                   f"{sig} | {verdict} |")
    return "\n".join(out)


def write_report(directory: Path, d: Diagnosis, meas: Measured, text: str,
                 model_out: str | None) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from leveler.analysis.diagnose import BANDS_HZ, residual
    from leveler.analysis.plots import block_means, plot_asd
    from leveler.analysis.predict import Predictor
    from leveler.analysis.spectral import lpsd

    directory.mkdir(parents=True, exist_ok=True)
    start = int((d.span_s[0] - meas.t_s[0]) / meas.dt_s)
    span = slice(start, len(meas.y_m))
    r0 = residual(meas, Predictor(meas.config.plant, meas), span)
    # Without an effect the model is left as it is (nothing is written, whatever the
    # in-tolerance recalibration moved): one model to draw, not a "fitted" twin of it.
    if d.effects:
        after = Predictor(d.params or meas.config.plant, meas)
        after.rebase(d.model)
        r1 = residual(meas, after, span)
        residuals = {"nominal model": r0, "fitted model": r1}
        fitted = "fitted model"
    else:
        r1 = r0
        fitted = ("nominal = fitted model "
                  f"(no effect {'found' if d.candidates else 'searched for'})")
        residuals = {fitted: r0}
    fs = 1.0 / meas.dt_s

    plot_asd([(f"residual, {name}", lpsd(r, fs)) for name, r in residuals.items()],
             directory / "residual_asd.png",
             ylabel="residual ASD [m/√Hz]", title=f"diagnose: {Path(meas.path).name}")

    fig = Figure(figsize=(9, 6), layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True)
    y = meas.y_m[span] - meas.y_m[span].mean()
    t, (measured, model, *averaged) = block_means(meas.t_s[span] / 3600, y,
                                                  y - r1 + r1.mean(), *residuals.values())
    top.plot(t, measured * 1e9, lw=0.8, label="measured")
    top.plot(t, model * 1e9, lw=0.8, label=fitted)
    top.set_ylabel("sensor [nm]")
    top.legend()
    top.set_title(f"{Path(meas.path).name}: {(t[1] - t[0]) * 3600:.0f} s averages")
    for name, r in zip(residuals, averaged, strict=True):
        bottom.plot(t, r * 1e9, lw=0.8, label=f"residual, {name}")
    bottom.set_xlabel("time [h]")
    bottom.set_ylabel("residual [nm]")
    bottom.legend()
    fig.savefig(directory / "timeseries.png", dpi=110)

    def norm(band: str, key: str) -> str:
        v = d.gap_normalised.get(band)
        return "n/a" if not v else f"{v[key]:.3g}"

    rows = "\n".join(
        f"| {band} | {_nm(d.gap_before['band_rms_m'][band])} | "
        f"{_nm(d.gap_after['band_rms_m'][band])} | {norm(band, 'before')} | "
        f"{norm(band, 'after')} |" for band in BANDS_HZ)
    found = "\n".join(
        f"- **{f.effect.name}**: {f.effect.describe()}\n"
        + "".join(f"  - `{k}` = {getattr(f.effect, k):.6g} ± {v:.2g}\n"
                  for k, v in f.sigma.items())
        for f in d.effects) or "- none: the model explains the log as well as its noise allows"
    (directory / "summary.md").write_text(
        f"# Model diagnosis of `{Path(meas.path).name}`\n\n"
        f"Model: {meas.model_source}. Analysed {d.span_s[0]:.0f}-{d.span_s[1]:.0f} s; "
        f"temperature {'used' if meas.sig.temperature_k is not None else 'not logged'}.\n\n"
        f"```\n{text}\n```\n\n## Effects found\n\n{found}\n\n"
        f"## Candidates of the last round, ranked by held-out evidence\n\n"
        f"{ranked_table(d)}\n\n"
        f"## Gap between model and measurement (residual RMS)\n\n"
        f"Power over the noise spectrum: the held-out part's residual periodogram over the "
        f"noise spectrum fitted to what the fitted model leaves, mean per band (1 = noise).\n\n"
        f"| band | nominal model [nm] | fitted model [nm] | nominal, power over noise | "
        f"fitted, power over noise |\n|---|---|---|---|---|\n"
        f"| all | {_nm(d.gap_before['rms_m'])} | {_nm(d.gap_after['rms_m'])} | | |\n"
        f"{rows}\n\n"
        f"![residual ASD](residual_asd.png)\n\n![time series](timeseries.png)\n\n"
        + (f"Fitted model: `{model_out}`\n" if model_out else ""))


def _nm(v: float | None) -> str:
    return "n/a" if v is None else f"{v * 1e9:.3g}"


def null_calibration(meas: Measured, runs: int, jobs: int | None,
                     progress: Stages) -> NullCalibration | None:
    """The cached calibration for this log's model and shape, made now (and cached) if
    `runs` asks for more runs than the cache holds; None without either."""
    from leveler.analysis import nullcal

    if runs < 0:
        raise LogError(f"--null-runs {runs}: give a number of runs >= 0")
    key = nullcal.cache_key(meas)
    cached = nullcal.load_cached(key)
    if runs == 0 or (cached is not None and cached.runs >= runs):
        return cached
    cal = nullcal.calibrate(meas, runs, jobs=max(jobs or os.cpu_count() or 1, 1), key=key,
                            progress=lambda done, total: progress("null calibration", done, total))
    path = nullcal.save(cal)
    print(f"leveler diagnose: null calibration of {runs} runs in {cal.wall_s:.0f} s "
          f"cached in {path}", file=sys.stderr)
    return cal


def run(args: argparse.Namespace) -> int:
    from leveler.analysis.diagnose import diagnose
    from leveler.analysis.predict import load_measured
    from leveler.cli.progress import Stages, fraction, reading
    from leveler.daemon.persist import write_atomic
    from leveler.log.reader import partial_note
    from leveler.settings import load_config

    with reading(args.log, quiet=args.json) as b:
        meas = load_measured(args.log, args.model, fraction(b))
    if meas.incomplete:
        note = partial_note(args.log, meas.incomplete, len(meas.y_m), meas.live)
        print(f"leveler diagnose: {note}", file=sys.stderr)
    with Stages("diagnose", quiet=args.json) as stages:
        cal = null_calibration(meas, args.null_runs, args.jobs, stages)
        d = diagnose(meas, max_effects=args.max_effects,
                     thresholds=None if cal is None else cal.thresholds,
                     jobs=max(args.jobs or os.cpu_count() or 1, 1), progress=stages)
    model_out = None
    if d.effects:
        out = Path(args.model_out) if args.model_out else default_model_path(args.log)
        if out.resolve() == Path(args.log).resolve() or (
                args.model and out.resolve() == Path(args.model).resolve()):
            raise LogError(f"{out}: refusing to overwrite the log or the input model; "
                           "choose another --model-out")
        recal = None if d.params is None else recalibrated_values(meas.config.plant, d.params)
        write_atomic(out, model_text(meas.model_text, [f.effect for f in d.effects],
                                     f"from {Path(args.log).name}", recal), load_config)
        model_out = str(out)
    text = summary(d, model_out, cal)
    if args.report:
        write_report(Path(args.report), d, meas, text, model_out)
    print(json.dumps(result_json(d, meas, model_out, cal)) if args.json else text)
    return 0
