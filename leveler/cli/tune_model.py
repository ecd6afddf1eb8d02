"""`leveler tune --suggest --model FITTED.toml`: controller additions against what a fitted
model names (a notch for a mode, resonant terms for a periodic disturbance, a temperature
feedforward for a temperature coupling), each checked over the model's tolerances where it
touches the loop's stability, with what a simulated run of the model predicts they do."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

from leveler.daemon.client import Client, ClientError

if TYPE_CHECKING:  # the config (numpy) and the analysis (python-control) are imported when a
    # suggestion is made, so `leveler status` and the other socket verbs start in ~0.1 s
    from leveler.analysis.periodic import Disturbance
    from leveler.loop.pid import ControllerConfig
    from leveler.settings import Config


def running_config(args: argparse.Namespace) -> str:
    """--config, else the running daemon's config file, else config/sim.toml."""
    if args.config is not None:
        return str(args.config)
    try:
        with Client(args.socket) as client, client.reading():
            return str(client.request("status")["status"]["config_path"])
    except ClientError:
        return "config/sim.toml"


def suggest_from_model(args: argparse.Namespace) -> dict[str, Any]:
    """Print what the model's named effects call for; returns it as tune values (on top of
    the running config's controller and at its loop rate). A mode is answered first, so
    resonant terms are designed on the loop with its notch."""
    from leveler.analysis import notch, periodic
    from leveler.settings import load_config

    config = running_config(args)
    cfg, _ = load_config(Path(config))
    model, _ = load_config(Path(args.model))
    mode = notch.named_mode(model.plant)
    d = periodic.named_disturbance(model.plant)
    coupled = model.plant.effects.temperature_coupling is not None
    if mode is None and d is None and not coupled:
        raise ClientError(f"--model {args.model}: it names no periodic disturbance (a "
                          "[plant.effects.periodic_disturbance], or a [plant.cooler] with a "
                          "peak_to_peak_rad), no mode ([plant.effects.extra_resonance]) and no "
                          "temperature coupling; `leveler diagnose LOG` writes them when it "
                          "finds them")
    at_rate = dataclasses.replace(model, loop=cfg.loop)
    print(f"plant model from {args.model}; controller and loop rate from {config}")
    values: dict[str, Any] = {}
    c = cfg.controller
    if mode is not None:
        values |= _suggest_notch(args, at_rate, c)
        c = dataclasses.replace(c, **_tuples(values))
    if d is not None:
        if values:
            print()
        values |= _suggest_periodic(args, at_rate, c, d)
    if coupled:
        if values:
            print()
        values |= _suggest_feedforward(args, config, cfg, dataclasses.replace(
            at_rate, controller=dataclasses.replace(c, **_tuples(values))))
    return values


NO_FEEDFORWARD = {"feedforward_gains_v_per_k": (), "feedforward_lags_s": (),
                  "feedforward_lags2_s": ()}


def _suggest_feedforward(args: argparse.Namespace, config: str, cfg: Config,
                         model: Config) -> dict[str, Any]:
    """Print the temperature feedforward the model's paths call for and what it buys;
    returns it as tune values when it is worth it and the running stand has a thermometer.
    It is an open-loop path: it cannot change the loop's stability or margins."""
    from leveler.analysis import feedforward

    ff = feedforward.design(model.plant)
    assert ff is not None  # the model has a temperature coupling
    # "as it is": the running loop without any feedforward it already has (the model's
    # stand may have no thermometer to feed one)
    model = dataclasses.replace(model, controller=dataclasses.replace(
        model.controller, **NO_FEEDFORWARD))
    paths = feedforward.temperature_paths(model.plant)
    if args.predict_hours > 0:
        b = feedforward.bound(model, args.predict_hours * 3600.0, ff=ff,
                              interval_s=cfg.thermometer.interval_s)
        print(feedforward.report(paths, b, ff))
        if not b.worth_it:
            return {}
    else:
        print("The model ties the tilt to the temperature: " + "; ".join(paths) + ".\n"
              f"Suggested feedforward ({ff.describe()}), not simulated (--predict-hours 0):\n"
              + "\n".join(feedforward.toml_lines(ff)))
    if cfg.thermometer.backend == "none":
        print(f"{config} reads no thermometer, so the feedforward cannot run there: add a "
              "[thermometer] table (backend \"modbus\" with its [thermometer.modbus], or "
              "\"sim\" on the simulated stand; docs/configuration.md), restart the daemon, "
              "and suggest again with --apply.")
        return {}
    print("It adds to the command outside the loop, so the loop's stability and margins "
          "stay as they are.")
    if args.log is not None:
        print(_replayed(args.log, args.model, feedforward.values(ff),
                        [(f, "") for f in FEEDFORWARD_HZ], "the feedforward"))
    return feedforward.values(ff)


FEEDFORWARD_HZ = (3e-4, 5e-4, 1e-3, 2e-3)  # where a thermal path's tilt lives


def _tuples(values: dict[str, Any]) -> dict[str, Any]:
    """Tune values (lists on the wire) as controller config fields (tuples)."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}


def _suggest_notch(args: argparse.Namespace, model: Config,
                   c: ControllerConfig) -> dict[str, Any]:
    from leveler.analysis import notch, periodic

    try:
        design = notch.design(model.plant, model.loop.rate_hz, c)
    except ValueError as exc:
        raise ClientError(f"--suggest --model: {exc}") from None
    why_not = notch.not_needed(design)
    if why_not:
        print(f"The model names a mode: {notch.mode_text(design.mode)}.\n{why_not}")
        return {}
    pred = None
    if args.predict_hours > 0:
        pred = periodic.predict(model, c, design.controller, [design.mode.frequency_hz],
                                args.predict_hours * 3600.0)
    print(notch.report(design, pred))
    if args.log is not None:
        print(f"(--log {args.log}: the replay what-if shows the reading, where a notch leaves "
              "the mode by design, as the table stops following it; the true tilt above is "
              "what it changes)")
    why = periodic.refusal(design.ours, design.theirs)
    if why:
        raise ClientError(f"the suggested notch is refused: {why}")
    return notch.values(design)


def _suggest_periodic(args: argparse.Namespace, model: Config, c: ControllerConfig,
                      d: Disturbance) -> dict[str, Any]:
    """Print resonant terms against the model's periodic disturbance; returns them as tune
    values."""
    from leveler.analysis import periodic

    rate = model.loop.rate_hz
    try:
        terms = periodic.design(model.plant, rate, c, d.period_s)
    except ValueError as exc:  # said, and the rest of the model still answered
        print(f"The model names a periodic disturbance: {d.source}, period {d.period_s:g} s. "
              f"No resonant terms: {exc}.")
        return {}
    values = {"periodic_period_s": terms.period_s,
              "periodic_gains_v_per_m_s": list(terms.gains_v_per_m_s),
              "periodic_phases_rad": list(terms.phases_rad),
              "periodic_radius": terms.radius}
    new = dataclasses.replace(c, **_tuples(values))
    ours = periodic.check(model.plant, rate, new)
    theirs = periodic.check(model.plant, rate, c)
    pred = None
    if args.predict_hours > 0:
        pred = periodic.predict(model, c, new, periodic.lines_hz(d.period_s),
                                args.predict_hours * 3600.0)
    print(periodic.report(d, terms, c, ours, theirs, pred))
    if args.log is not None:
        print(_replayed(args.log, args.model, values,
                        [(h / terms.period_s, f" (line {h})") for h in range(1, 6)], "the terms"))
    if not theirs.ok:
        print(f"note: the current loop itself misses {periodic.MIN_GAIN_MARGIN_DB:g} dB / "
              f"{periodic.MIN_PHASE_MARGIN_DEG:g} deg on this model; the terms are judged "
              "against it (check the PID with `leveler tune --suggest`)")
    why = periodic.refusal(ours, theirs)
    if why:
        raise ClientError(f"the suggested terms are refused: {why}")
    return values


def _replayed(log: str, model: str, values: dict[str, Any], lines: list[tuple[float, str]],
              what: str) -> str:
    """The replay what-if of `log` with `values` (tune values) on its logged controller:
    the reading at `lines` ([Hz], label), as logged and as predicted."""
    from leveler.analysis.diagnose import warmup_samples
    from leveler.analysis.predict import Predictor, load_measured
    from leveler.analysis.replay import what_if
    from leveler.analysis.spectral import asd_at
    from leveler.errors import LogError

    try:
        meas = load_measured(log, model=model)
    except LogError as exc:
        raise ClientError(f"--log: {exc}") from None
    if meas.controller is None:
        raise ClientError(f"--log {log}: it does not say what its controller was (not a "
                          f"leveler log), so there is nothing to add {what} to")
    pred = Predictor(meas.config.plant, meas, ringing=True)
    span = slice(warmup_samples(meas, pred), len(meas.y_m))
    fs = 1.0 / meas.dt_s
    y = meas.y_m[span]
    lines = [(f, label) for f, label in lines if f * len(y) / fs >= 20]
    if not lines:
        return f"(--log {log}: too short to resolve the frequencies it would act at)"
    try:
        replayed = what_if(meas, pred, dataclasses.replace(meas.controller, **_tuples(values)))
    except ValueError as exc:
        raise ClientError(f"--log: {exc}") from None
    freqs = [f for f, _ in lines]
    logged = asd_at(y, fs, freqs)
    out = [f"\nOn {log}'s own run (the replay what-if: its logged controller plus {what}; "
           "the reading) [nm/rtHz]:", f"{'':<34}{'suggested':<22}as logged"]
    out += [f"{f'ASD at {f * 1e3:.3g} mHz{label}':<34}{a * 1e9:<22.3g}{b * 1e9:.3g}"
            for (f, label), a, b in zip(lines, asd_at(replayed[span], fs, freqs), logged,
                                        strict=True)]
    return "\n".join(out)


MIN_DRIFT_REL = 0.002  # a retracked period this close to the terms' keeps them


def retrack(args: argparse.Namespace) -> dict[str, Any]:
    """Print the period the running terms' disturbance has in `args.retrack`'s command and,
    when it drifted, the terms re-designed there (on the running PID, the running config's
    plant model or --model's); returns them as tune values ({} when they stay)."""
    from leveler.analysis import periodic
    from leveler.analysis import retrack as rt
    from leveler.errors import LogError
    from leveler.log.reader import read_log
    from leveler.settings import load_config

    config = running_config(args)
    cfg, _ = load_config(Path(config))
    model = cfg if args.model is None else load_config(Path(args.model))[0]
    c = cfg.controller
    terms = c.periodic_terms()
    if terms is None:
        raise ClientError(f"{config}: the controller has no resonant terms to retrack (no "
                          "[controller] periodic_*); `leveler tune --suggest --model` adds them")
    try:
        samples = read_log(args.retrack).samples
    except (LogError, OSError) as exc:
        raise ClientError(f"--retrack: {exc}") from None
    span = rt.last_engaged(samples.get("state", []))
    if span.stop - span.start < 2:
        raise ClientError(f"--retrack {args.retrack}: the loop was never engaged in it")
    try:
        track = rt.estimate_period(samples["t_s"][span], samples["applied_v"][span],
                                   terms.period_s)
    except ValueError as exc:
        raise ClientError(f"--retrack {args.retrack}: {exc}") from None
    print(f"controller and loop rate from {config}; plant model from "
          f"{config if args.model is None else args.model}")
    print(f"{args.retrack}: {rt.describe(track, terms.period_s)}.")
    drift = rt.drift_rel(track, terms.period_s)
    if not track.clear or track.at_edge:
        print("The terms stay as they are.")
        return {}
    if abs(drift) < MIN_DRIFT_REL:
        print(f"Within {MIN_DRIFT_REL:.1%} of the terms' period: they stay as they are.")
        return {}
    rate = cfg.loop.rate_hz
    try:
        new = periodic.design(model.plant, rate, c, track.period_s)
    except ValueError as exc:
        raise ClientError(f"--retrack: {exc}") from None
    values = {"periodic_period_s": new.period_s,
              "periodic_gains_v_per_m_s": list(new.gains_v_per_m_s),
              "periodic_phases_rad": list(new.phases_rad), "periodic_radius": terms.radius}
    ours = periodic.check(model.plant, rate, dataclasses.replace(c, **_tuples(values)))
    theirs = periodic.check(model.plant, rate, c)
    print(f"Re-designed: resonant terms at harmonics 1-{len(new.gains_v_per_m_s)} of "
          f"{new.period_s:.5g} s (were {len(terms.gains_v_per_m_s)} of {terms.period_s:g} s):")
    print("\n".join(periodic.terms_toml(new) + periodic.margin_rows(ours, theirs)))
    why = periodic.refusal(ours, theirs)
    if why:
        raise ClientError(f"the re-designed terms are refused: {why}")
    return values


def suggest_boost(args: argparse.Namespace) -> dict[str, Any]:
    """Print the boosted PID (leveler.analysis.boost) on the running controller and what a
    simulated run of the model predicts it does; returns its gains as tune values."""
    from leveler.analysis import boost, periodic
    from leveler.settings import load_config

    config = running_config(args)
    cfg, _ = load_config(Path(config))
    model = cfg if args.model is None else load_config(Path(args.model))[0]
    at_rate = dataclasses.replace(model, loop=cfg.loop)
    c = cfg.controller
    print(f"plant model from {args.model or config}; controller and loop rate from {config}")
    b = boost.design(at_rate.plant, cfg.loop.rate_hz, c)
    if b is None:
        print(f"No boost: no double integral within the search keeps "
              f"{periodic.MIN_GAIN_MARGIN_DB:g} dB and {periodic.MIN_PHASE_MARGIN_DEG:g} deg "
              "on every model while at least doubling the worst suppression in 1-10 mHz.")
        return {}
    print(boost.report(b, c))
    if args.predict_hours > 0:
        d = periodic.named_disturbance(at_rate.plant)
        lines = [] if d is None else periodic.lines_hz(d.period_s)
        pred = periodic.predict(at_rate, c, b.controller, lines, args.predict_hours * 3600.0)
        print("\n".join(periodic.predicted_rows(
            pred, [f"ASD at {f * 1e3:.3g} mHz (line {j + 1})" for j, f in enumerate(lines)])))
    return boost.values(b)
