"""The `leveler` command: one subcommand per job, each with --help that answers questions."""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
from collections.abc import Sequence

from leveler.cli.durations import parse_duration
from leveler.daemon.client import ClientError
from leveler.emulate.faults import parse_fault
from leveler.errors import ControlError, LogError
from leveler.typed_config import ConfigError


def _duration(text: str) -> float:
    try:
        return parse_duration(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _cmd_run(args: argparse.Namespace) -> int:
    from leveler.daemon.service import run_daemon

    return run_daemon(args.config, duration_s=args.duration)


def _cmd_sim(args: argparse.Namespace) -> int:
    from leveler.cli.sim import run_sim_command

    return run_sim_command(args)


def _cmd_asd(args: argparse.Namespace) -> int:
    from leveler.cli.asd import run_asd_command

    return run_asd_command(args)


def _cmd_recover(args: argparse.Namespace) -> int:
    from leveler.log.reader import recover

    n = recover(args.log, args.out)
    print(f"recovered {n} messages from {args.log} into {args.out}")
    return 0


def _cmd_import_csv(args: argparse.Namespace) -> int:
    from leveler.log.import_csv import run_import_csv_command

    return run_import_csv_command(args)


def _cmd_replay(args: argparse.Namespace) -> int:
    from leveler.analysis.replay import run_replay_command

    return run_replay_command(args)


def _cmd_diagnose(args: argparse.Namespace) -> int:
    from leveler.cli.diagnose import run_diagnose_command

    return run_diagnose_command(args)


def _cmd_modulate(args: argparse.Namespace) -> int:
    from leveler.cli.modulate import run_modulate_command

    return run_modulate_command(args)


def _cmd_design_ip(args: argparse.Namespace) -> int:
    from leveler.cli.design import run_design_ip_command

    return run_design_ip_command(args)


def _cmd_analyze_stiffness(args: argparse.Namespace) -> int:
    from leveler.cli.analyze_stiffness import run_stiffness_command

    return run_stiffness_command(args)


def _cmd_analyze_two_stage(args: argparse.Namespace) -> int:
    from leveler.cli.analyze_two_stage import run_two_stage_command

    return run_two_stage_command(args)


def _cmd_calibrate_com(args: argparse.Namespace) -> int:
    from leveler.cli.calibrate_com import run_com_command

    return run_com_command(args)


def _cmd_emulate(args: argparse.Namespace) -> int:
    from leveler.cli.emulate import run_emulate_command

    return run_emulate_command(args)


def _gains(text: str) -> tuple[float, float, float]:
    from leveler.analysis.replay import parse_gains

    return parse_gains(text)


def _cmd_control(args: argparse.Namespace) -> int:
    from leveler.daemon.client import Client, format_status, run_watch

    # reload may load python-control into the daemon first: seconds on a busy machine
    with (Client(args.socket, timeout_s=60.0 if args.command == "reload" else 5.0)
          as client, client.reading()):
        if args.command == "status":
            st = client.request("status")["status"]
            if args.json:
                import json

                print(json.dumps(st))
            else:
                print(format_status(st))
        elif args.command == "watch":
            run_watch(client, args.rate, args.count)
        elif args.command == "rotate":
            print(f"logging to {client.request('rotate')['path']}")
        elif args.command == "reload":
            from leveler.daemon.client import format_reload

            print(format_reload(client.request("reload", accept_dropped=args.accept_dropped,
                                               force=args.force)))
        else:
            print(f"state: {client.request(args.command)['state']}")
    return 0


def _cmd_tune(args: argparse.Namespace) -> int:
    from leveler.cli.tune import run_tune_command

    return run_tune_command(args)


def _add_socket(p: argparse.ArgumentParser) -> None:
    p.add_argument("--socket", default=None,
                   help="control socket of the daemon (default: $LEVELER_SOCKET, then "
                   "/run/leveler/control.sock, then your own runtime directory's)")


def _add_control_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    simple = {
        "start": "close the loop (bumpless, from the voltage the piezo holds now)",
        "stop": "open the loop: keep sampling and logging, hold the piezo where it is",
        "reset": "leave the fault state after the cause is fixed (the loop stays open)",
        "rotate": "close the current log file and start a new one",
    }
    for name, text in simple.items():
        p = sub.add_parser(name, help=text, description=f"{text[0].upper()}{text[1:]}. Talks "
                           "to the running daemon over its control socket; needs membership of "
                           "the daemon's group (or root).")
        _add_socket(p)
        p.set_defaults(func=_cmd_control)
    st = sub.add_parser("status", help="state, reading, piezo, gains, loop timing and log of "
                        "the running daemon", description="Ask the running daemon how it is: "
                        "state (idle, engaged, fault and why), the last reading and the tilt it "
                        "means, piezo voltage, controller settings, loop period statistics and "
                        "overruns, and the log file.")
    st.add_argument("--json", action="store_true", help="print the status as one JSON object")
    _add_socket(st)
    st.set_defaults(func=_cmd_control)
    rl = sub.add_parser(
        "reload", help="re-read the daemon's config file (as SIGHUP), with its diff",
        description="Ask the running daemon to re-read its config file, as `systemctl reload "
        "leveler` (SIGHUP) does, and print what changed. The file is applied only whole: it "
        "must be valid, set every key the running file set (a file cut short at a line "
        "boundary is still valid TOML, and its missing keys would take their defaults), and "
        "new gains must make a loop the plant model predicts stable. [controller] applies at "
        "once (bumpless); other sections at the next restart. Every applied reload logs its "
        "diff of effective values (journal and the log's `reload` event).")
    rl.add_argument("--accept-dropped", action="store_true",
                    help="apply even though the file no longer sets keys the running one set "
                    "(they go back to their defaults)")
    rl.add_argument("--force", action="store_true",
                    help="apply gains even if the plant model predicts an unstable loop")
    _add_socket(rl)
    rl.set_defaults(func=_cmd_control)
    w = sub.add_parser("watch", help="live view of the running loop: values and a small trend",
                       description="Stream samples from the running daemon at a decimated rate "
                       "and show them with a trend of the last 40 sensor readings. Ctrl-C ends "
                       "it (the daemon carries on).")
    w.add_argument("--rate", type=float, default=2.0, help="samples per second (default: 2)")
    w.add_argument("--count", type=int, default=None, help="stop after this many samples")
    _add_socket(w)
    w.set_defaults(func=_cmd_control)
    t = sub.add_parser(
        "tune", help="change gains, setpoint, limits or slew live; or suggest gains",
        description="Change controller settings of the running daemon. Values are checked "
        "before they are applied; gain changes are bumpless (the piezo command does not jump). "
        "--persist also writes them into the daemon's config file (atomically, comments kept). "
        "New gains that the plant model (python-control) predicts make the loop unstable are "
        "refused unless --force. "
        "With --suggest, propose gains from the configured plant model (python-control) and "
        "print margins; --apply sends them.")
    t.add_argument("--kp", type=float, help="proportional gain [V/m]")
    t.add_argument("--ki", type=float, help="integral gain [V/(m s)]")
    t.add_argument("--kd", type=float, help="derivative gain [V s/m]")
    t.add_argument("--setpoint", type=float, help="setpoint of the sensor reading [m] (SI: "
                   "1e-6 is 1 um; refused beyond +-1 mm)")
    t.add_argument("--min-v", type=float, help="lower output limit [V]; a range that excludes "
                   "the present output moves the piezo into it at once, at the actuator's own "
                   "slew limit, not the controller's (--slew): limits protect the hardware, "
                   "the slew only smooths")
    t.add_argument("--max-v", type=float, help="upper output limit [V] (as --min-v)")
    t.add_argument("--slew", type=float, help="output slew limit [V/s]; inf: no limit")
    t.add_argument("--persist", action="store_true", help="also write the values to the "
                   "daemon's config file")
    t.add_argument("--force", action="store_true", help="apply gains even if the plant model "
                   "predicts an unstable loop (refused otherwise)")
    t.add_argument("--suggest", action="store_true", help="propose gains from the plant model")
    t.add_argument("--bandwidth", type=float, default=None,
                   help="with --suggest: wanted unity-gain frequency [Hz] (default: the highest "
                   "the margins allow)")
    t.add_argument("--phase-margin", type=float, default=60.0,
                   help="with --suggest: wanted phase margin [deg] (default: 60)")
    t.add_argument("--plot", default=None, help="with --suggest: Bode/Nyquist plot (PNG)")
    t.add_argument("--config", default=None, help="with --suggest: plant model config "
                   "(default: the running daemon's, else config/sim.toml)")
    t.add_argument("--apply", action="store_true", help="with --suggest: send the proposal to "
                   "the daemon")
    _add_socket(t)
    t.set_defaults(func=_cmd_tune)
    m = sub.add_parser(
        "modulate", help="square-wave tilt modulation by the piezo; the pendulum's response",
        description="Drive the piezo in a square wave about the voltage it holds, with the "
        "loop open, and measure the inverted pendulum's step: peak to peak, per piezo volt, "
        "as platform tilt, and against what the config's piezo geometry (stroke / support "
        "spacing) predicts. The running daemon executes it as a logged procedure (state "
        "`modulating`, `procedure` events, every sample in the log); it refuses while the "
        "loop is engaged unless --force, which opens the loop for the wave and closes it "
        "again afterwards. `leveler stop` aborts a wave; a fault ends it with the piezo safe. "
        "With --sim the same procedure runs on the simulated stand in virtual time.")
    m.add_argument("--amplitude-v", type=float, required=True,
                   help="piezo swing about the held voltage [V]: +amplitude for the first half "
                   "of each period, -amplitude for the second (peak to peak = 2 x amplitude)")
    m.add_argument("--period", type=_duration, required=True,
                   help="square-wave period, e.g. 60s or 5min (at least 4 loop periods)")
    m.add_argument("--cycles", type=int, default=3, help="number of periods (default: 3)")
    m.add_argument("--force", action="store_true",
                   help="modulate even if the loop is engaged (it closes again afterwards)")
    m.add_argument("--json", action="store_true", help="print the result as one JSON object")
    m.add_argument("--sim", action="store_true",
                   help="run on the simulated stand in virtual time instead of the daemon")
    m.add_argument("--config", default=None,
                   help="with --sim: the stand's config (default: config/sim.toml)")
    m.add_argument("--settle", type=_duration, default=0.0,
                   help="with --sim: idle time before the wave (default: 0)")
    m.add_argument("--seed", type=int, default=None,
                   help="with --sim: disturbance and noise seed (default: [sim] seed)")
    m.add_argument("--plot", default=None, help="with --sim: time-series plot (PNG)")
    m.add_argument("--tp-peak-to-peak-m", type=float, default=None,
                   help="the torsion pendulum's step under the same wave, read off the thrust "
                   "stand [m]: gives the inverted/torsion ratio and the roll/pitch split "
                   "(with --sim it is simulated)")
    m.add_argument("--tp-com-x-m", type=float, default=1e-4,
                   help="torsion pendulum's centre-of-mass offset along x, coupling roll [m] "
                   "(default: %(default)g; measure yours with calibrate-com)")
    m.add_argument("--tp-com-y-m", type=float, default=None,
                   help="its offset along y, coupling pitch [m] (default: the model's, "
                   "0.27 mm)")
    m.add_argument("--tilt-axis-deg", type=float, default=30.0,
                   help="with --sim: the piezo tilts the platform along this angle from the "
                   "torsion pendulum's pitch axis (default: %(default)g)")
    _add_socket(m)
    m.set_defaults(func=_cmd_modulate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="leveler",
        description="Real-time drag-free leveling of a tilting lab table: an inverted pendulum "
        "senses the tilt, a PID drives a piezo under one support, every sample goes to MCAP.",
        epilog="Units are SI throughout (m, rad, V, s, K). docs/ describes the config and the log.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser(
        "run", help="run the leveling daemon in the foreground (what systemd starts)",
        description="Run the control loop in real time on the backend the config names "
        "(backend = \"sim\" runs the simulated plant). Prints a status line every "
        "loop.status_interval_s; logs every sample to <log.dir>/leveler-<UTC time>Z.mcap. "
        "Ctrl-C or SIGTERM stops it cleanly: actuator to its safe voltage, log finished.")
    run.add_argument("--config", required=True, help="TOML config file (e.g. config/sim.toml)")
    run.add_argument("--duration", type=_duration, default=None,
                     help="stop by itself after this long (e.g. 90s, 10m); default: run until "
                     "signalled")
    run.set_defaults(func=_cmd_run)

    sim = sub.add_parser(
        "sim", help="simulate a long run in virtual time; report how much tilt the loop removed",
        description="Run the daemon's loop on the simulated plant in virtual time, closed loop "
        "and, with the same disturbance realization, open loop (piezo held). Reports the "
        "amplitude spectral density at 0.1 mHz, 1 mHz and 10 mHz of the in-loop sensor "
        "(pendulum-end displacement) and of the true platform tilt (out of loop).")
    sim.add_argument("--config", default="config/sim.toml",
                     help="TOML config (default: %(default)s)")
    sim.add_argument("--duration", type=_duration, default=parse_duration("24h"),
                     help="virtual time to simulate: 3600s, 90m, 6h, 1d (default: 24h; "
                     "0.1 mHz needs several hours)")
    sim.add_argument("--seed", type=int, default=None,
                     help="disturbance and noise seed (default: [sim] seed of the config)")
    sim.add_argument("--out", default=None, help="write the closed-loop run to this MCAP file")
    sim.add_argument("--json", action="store_true",
                     help="print one JSON object on stdout instead of the table")
    sim.add_argument("--plot", default=None, help="save open vs closed loop ASD plot (PNG)")
    sim.set_defaults(func=_cmd_sim)

    asd = sub.add_parser(
        "asd", help="amplitude spectral density of a logged channel (LPSD, log-spaced)",
        description="Estimate the ASD of one channel of a leveler MCAP log with the LPSD "
        "method (Troebs & Heinzel 2006), which keeps many averages at high frequency and "
        "still reaches 0.1 mHz in a long log. Channels: any numeric field of the sample "
        "topic (sensor_m, applied_v, error_m, ...) or, in simulated logs, the truth topic "
        "(tilt_rad, thermal_tilt_rad, pendulum_rad, ...). Values a daemon logged as null "
        "(held bad readings, driver errors) are bridged by linear interpolation if they are "
        "at most 1% of the record and no gap is longer than 10 s, and cut off if they are at "
        "its start or end; a note on stderr says how many. Beyond that the log is refused.")
    asd.add_argument("log", help="MCAP log written by leveler")
    asd.add_argument("--channel", default="sensor_m",
                     help="field to analyse (default: %(default)s)")
    asd.add_argument("--compare", default=None,
                     help="a second log (e.g. open loop) drawn and tabulated against the first")
    asd.add_argument("--plot", default=None, help="save the ASD plot as PNG")
    asd.add_argument("--json", action="store_true", help="print the spectrum as JSON")
    asd.set_defaults(func=_cmd_asd)

    rec = sub.add_parser(
        "recover", help="copy everything readable from a crashed log into a complete file",
        description="A log cut short (power cut, SIGKILL) has no index; leveler's own reader "
        "still reads it, and this writes a complete copy that any MCAP tool opens.")
    rec.add_argument("log", help="the damaged MCAP file (left untouched)")
    rec.add_argument("--out", required=True, help="where to write the recovered copy")
    rec.set_defaults(func=_cmd_recover)

    imp = sub.add_parser(
        "import-csv", help="convert another system's CSV recording into a leveler MCAP log",
        description="Convert data recorded by another system into a leveler MCAP log, so "
        "replay, diagnose and asd can analyse it. FILE is UTF-8 text, comma-separated; blank "
        "lines and lines starting with # are skipped; the first other line is the header. "
        "Columns, named in the header (case-insensitive, any order): t_s (time [s], strictly "
        "increasing, uniformly sampled), actuator_V (voltage applied to the actuator [V]), "
        "sensor_m (displacement at the pendulum end [m]) and optionally temperature_K (table "
        "temperature [K]); other columns are ignored. Values are SI as given, not converted. "
        "At least 16 rows. A bad row (reported by line number) fails the import unless "
        "--skip-bad; no output is left behind on error. Details: docs/log-format.md, "
        "\"Importing other systems' data (CSV)\".")
    imp.add_argument("csv", metavar="FILE.csv", help="the CSV file to import (left untouched)")
    imp.add_argument("--out", required=True, metavar="LOG.mcap", help="the MCAP log to write")
    imp.add_argument("--skip-bad", action="store_true",
                     help="leave bad rows out (listed on stderr) instead of failing")
    imp.add_argument("--force", action="store_true", help="replace --out if it exists")
    imp.set_defaults(func=_cmd_import_csv)
    rp = sub.add_parser(
        "replay", help="how well the plant model predicts a log (residual, bands, what-if)",
        description="Drive the plant model with the logged actuator voltage (and the logged "
        "temperature, if any) and compare its prediction with the logged sensor reading. "
        "Prints the residual RMS, its RMS and mean ASD in the bands 0.1-1 mHz, 1-10 mHz, "
        "10-100 mHz and 0.1-1 Hz, and the fraction of the measured variance the model "
        "explains. The first minutes are skipped (the log may start out of equilibrium); "
        "the table's unknown offset is removed. The model is the config stored in the log "
        "unless --model names another (e.g. one written by `leveler diagnose`).")
    rp.add_argument("log", help="MCAP log written by leveler (or by `leveler import-csv`)")
    rp.add_argument("--model", default=None, help="config file whose [plant] is the model "
                    "(default: the config stored in the log)")
    rp.add_argument("--out", default=None, help="write measured, predicted and residual per "
                    "sample to this MCAP file (topic /leveler/replay)")
    rp.add_argument("--json", action="store_true", help="print one JSON object")
    rp.add_argument("--plot", default=None, help="save time-series overlay and ASDs (PNG)")
    rp.add_argument("--gains", type=_gains, default=None, metavar="KP,KI,KD",
                    help="what-if: rerun the controller with these gains [V/m, V/(m s), "
                    "V s/m] against the model and the disturbance the log implies; prints "
                    "the sensor ASD they would have given at 0.1, 1 and 10 mHz")
    rp.set_defaults(func=_cmd_replay)

    dg = sub.add_parser(
        "diagnose", help="find, name and fit what the plant model is missing",
        description="Replay the log, look for structure in the residual (spectral lines, "
        "coherence with the actuator and the temperature, a lattice in the readings, "
        "trends), fit each named effect (periodic_disturbance, temperature_coupling, "
        "actuator_delay, actuator_hysteresis, extra_resonance, sensor_gain_error, "
        "sensor_drift, adc_quantization) on the first two thirds of the log and keep it only "
        "if it predicts the last third better than its complexity penalty; repeat while one "
        "does. Writes the updated model (a plain config: `leveler sim --config` and "
        "`leveler replay --model` use it) next to the log as LOG.fitted.toml. Says so, and "
        "writes nothing, when no effect is missing.")
    dg.add_argument("log", help="MCAP log written by leveler (or by `leveler import-csv`)")
    dg.add_argument("--model", default=None, help="config file whose [plant] is the model "
                    "to test (default: the config stored in the log)")
    dg.add_argument("--model-out", default=None,
                    help="where to write the fitted model (default: LOG.fitted.toml)")
    dg.add_argument("--report", default=None, metavar="DIR",
                    help="write residual_asd.png, timeseries.png and summary.md here")
    dg.add_argument("--max-effects", type=int, default=4,
                    help="stop after this many effects (default: %(default)s)")
    dg.add_argument("--json", action="store_true",
                    help="print one JSON object: effects, gap_before, gap_after, model_out, "
                    "and every candidate tried with its scores")
    dg.set_defaults(func=_cmd_diagnose)
    em = sub.add_parser(
        "emulate", help="serve the simulated plant over the real device protocol",
        description="Stand in for the hardware: serve the simulated plant ([plant] of the "
        "config) through the protocol the config's drivers speak, at the addresses and "
        "with the scaling the config gives, so `leveler run --config` the same file levels "
        "it exactly as it would the real table. modbus: a Modbus TCP server at "
        "[sensor.modbus] host:port (input registers: the sensor; holding registers: the "
        "piezo). serial: a piezo amplifier ([actuator.serial] protocol) and a sensor "
        "controller on pseudo-terminals, linked at the config's port paths (which must be "
        "free paths, e.g. /tmp/leveler-piezo, not real devices); modbus with transport = "
        "\"rtu\" serves a pty linked at serial_port. Runs until Ctrl-C.")
    em.add_argument("kind", choices=["modbus", "serial"], help="which protocol to serve")
    em.add_argument("--config", required=True, help="the lab config to serve")
    em.add_argument("--seed", type=int, default=None,
                    help="disturbance and noise seed (default: [sim] seed)")
    em.add_argument("--fault", action="append", default=[], type=parse_fault,
                    metavar="T:KIND[:COUNT]",
                    help="spoil COUNT (default 1) replies from T seconds after the start; "
                    "repeatable. modbus KINDs: no_reply, exception (code 4), garbage, drop. "
                    "serial KINDs: piezo.X or sensor.X with X one of no_reply, garbage, "
                    "partial_line, drop, error. E.g. --fault 30:garbage --fault 60:exception:2")
    em.set_defaults(func=_cmd_emulate)

    design = sub.add_parser(
        "design", help="the paper's design procedures (ip: inverted-pendulum counterweight)",
        description="Design calculations from the paper, each a subcommand.")
    dsub = design.add_subparsers(dest="design_command", required=True, metavar="DESIGN")
    ip = dsub.add_parser(
        "ip", help="inverted-pendulum tilt amplifier: amplification N against counterweight",
        description="The paper's counterweight sweep (its Figure 8) with our geometry, not its "
        "Simscape model: a flexure of stiffness k (config [plant.pendulum]) carries a frame "
        "(mass m_f, centre of mass L_f above the pivot; default none) and a counterweight "
        "m_cw at height h_cw, so m g L_cm = g (m_f L_f + m_cw h_cw). For each counterweight "
        "mass it prints m g L_cm, the small-angle amplification N = 1 / (k / (m g L_cm) - 1) "
        "and the N = theta / phi of the full balance m g L_cm sin(theta + phi) = k theta "
        "solved at the reference tilt phi, with the equilibrium angle theta. The stability "
        "limit m g L_cm = k (small-angle N -> infinity) is marked; heavier counterweights are "
        "reported unstable. --target-n picks the mass for a requested N at phi (exactly, by "
        "the balance's closed-form inverse). The default stand is a 185 g mass 49.6 mm above "
        "a 0.1 N m/rad flexure: m g L_cm = 0.09 N m/rad, N = 9, the paper's example.",
        epilog="Example: leveler design ip --target-n 10 --plot ip.png. Units are SI; the "
        "table shows theta in mrad, the plot masses in g.")
    ip.add_argument("--config", default="config/sim.toml",
                    help="config whose [plant.pendulum] gives k and g; its com_length_m is "
                    "the default counterweight height (default: %(default)s)")
    ip.add_argument("--target-n", type=float, default=None, metavar="N",
                    help="pick the counterweight giving amplification N at the reference tilt")
    ip.add_argument("--tilt-rad", type=float, default=1e-3,
                    help="reference tilt phi for the non-linear N [rad] (default: %(default)g, "
                    "as in the paper)")
    ip.add_argument("--cw-height-m", type=float, default=None,
                    help="height of the counterweight's centre of mass above the pivot [m] "
                    "(default: the config's com_length_m)")
    ip.add_argument("--frame-mass-kg", type=float, default=0.0,
                    help="mass of the rest of the pendulum [kg] (default: 0)")
    ip.add_argument("--frame-com-m", type=float, default=0.0,
                    help="height of the frame's centre of mass above the pivot [m] "
                    "(default: 0)")
    ip.add_argument("--mass-kg", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
                    help="counterweight masses to sweep [kg] (default: 0.5 to 1.05 times the "
                    "stability limit; a range across the limit is fine)")
    ip.add_argument("--step-kg", type=float, default=None,
                    help="table step [kg] (default: a round step giving 6 to 15 rows)")
    ip.add_argument("--json", action="store_true",
                    help="print one JSON object (model, sweep, stability_limit, pick, plot)")
    ip.add_argument("--plot", default=None, metavar="FILE.png",
                    help="save N against counterweight mass, limit marked (PNG)")
    ip.set_defaults(func=_cmd_design_ip)
    an = sub.add_parser(
        "analyze", help="the paper's torsion-pendulum analyses on the simulator (stiffness, "
        "two-stage)", description="Simulated torsion-pendulum (thrust stand) analyses from "
        "the paper, each a subcommand. The pendulum obeys J theta'' + lambda theta' + K0 theta "
        "= F L + M g sin(pitch) l_cm,y + M g sin(roll) l_cm,x (leveler.sim.torsion).")
    asub = an.add_subparsers(dest="analyze_command", required=True, metavar="ANALYSIS")
    stf = asub.add_parser(
        "stiffness", help="thrust stiffness and compliance against base tilt; regimes; tilt "
        "budget (paper Figs. 3-6)",
        description="For each pivot stiffness K0 and thrust F, and each pitch tilt of a "
        "symmetric sweep, a square-wave thrust (0/F, 5 x 400 s at 5 Hz, 1 nm/rtHz sensor noise) "
        "drives the simulated pendulum, and a second-order thrust -> displacement transfer "
        "function is identified by least squares. Its 0 Hz value, with the sensor zeroed at "
        "the level rest position (the paper's definition), gives the compliance S = theta / "
        "(F L) and the stiffness K = 1 / S. The gravity torque does not change the pendulum's "
        "dynamics, it shifts its rest point; attributing that shift to the thrust makes "
        "S = (1 + r) / K0 with r = M g sin(tilt) l_cm / (F L): compliance linear in tilt "
        "(Fig. 6), stiffness close to a two-term exponential (Fig. 5). 'K incr.' is the "
        "stiffness fitted with a free offset: K0 at every tilt. Regimes: r > 0 softening, "
        "-1 < r < 0 stiffening, r < -1 negative stiffness (unstable as a balance). Tilt budget: "
        "the largest |tilt| with gravity torque <= 1/4 of F L, from the measured compliance "
        "slope. Fits and the regime table use the first K0; takes some seconds per K0 and F.",
        epilog="Example: leveler analyze stiffness --plot-dir out/ (transfer_1uN.png and "
        "transfer_0.1uN.png like Figs. 3, 4; stiffness.png, compliance.png, regimes.png). "
        "Units are SI; the tables show urad and uN.")
    stf.add_argument("--stiffness-nm-per-rad", type=float, nargs="+", default=[0.2, 0.02],
                     metavar="K0", help="pivot stiffnesses K0 [N m/rad] (default: 0.2 0.02, "
                     "the paper's); the first gets the fits")
    stf.add_argument("--thrust-n", type=float, nargs="+", default=[1e-6, 1e-7], metavar="F",
                     help="square-wave thrust amplitudes [N] (default: 1e-6 1e-7, the paper's); "
                     "the first gets the Fig. 5/6 fits")
    stf.add_argument("--max-tilt-rad", type=float, default=20e-6,
                     help="sweep pitch from -this to +this [rad] (default: %(default)g)")
    stf.add_argument("--tilt-step-rad", type=float, default=2.5e-6,
                     help="sweep step [rad] (default: %(default)g)")
    stf.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default: 0)")
    stf.add_argument("--json", action="store_true",
                     help="print one JSON object (model, identification, sweeps with points, "
                     "fits, regimes_seen, tilt_budget_rad)")
    stf.add_argument("--plot-dir", default=None, metavar="DIR",
                     help="write the figures (PNG) into DIR")
    stf.set_defaults(func=_cmd_analyze_stiffness)
    two = asub.add_parser(
        "two-stage", help="two-stage torsion pendulum: thrust recovered under base tilt "
        "(paper Fig. 17)",
        description="TP2 (the thrust balance, displacement mode) hangs on TP1, which a PID "
        "holds at null. Under base tilt TP2 reads F L + tau_2 and TP1's null-control torque "
        "balances F L + tau_A, with tau_2 = kappa tau_A, kappa = M2 L_cm2 / ((M1 + M2) L_cm1). "
        "A calibration run (thruster off, same tilt) measures kappa; the two-stage estimate "
        "(y2 - kappa b) / ((1 - kappa) L) removes the tilt, the single-stage estimate y2 / L "
        "(TP2 alone) does not. Prints both estimates' correlation with the true square-wave "
        "thrust and their rms error.",
        epilog="Example: leveler analyze two-stage --plot fig17.png. Units are SI.")
    two.add_argument("--tilt-amplitude-rad", type=float, default=3e-6,
                     help="base pitch amplitude [rad] (default: %(default)g, the paper's)")
    two.add_argument("--tilt-frequency-hz", type=float, default=0.01,
                     help="base pitch frequency [Hz] (default: %(default)g, the paper's)")
    two.add_argument("--thrust-n", type=float, default=1e-7,
                     help="square-wave thrust 0/F [N] (default: %(default)g)")
    two.add_argument("--thrust-period-s", type=float, default=200.0,
                     help="square-wave period [s] (default: %(default)g)")
    two.add_argument("--duration-s", type=float, default=1000.0,
                     help="length of each run [s] (default: %(default)g)")
    two.add_argument("--fs-hz", type=float, default=10.0,
                     help="sample and null-loop rate [Hz] (default: %(default)g)")
    two.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default: 0)")
    two.add_argument("--json", action="store_true", help="print one JSON object")
    two.add_argument("--plot", default=None, metavar="FILE.png",
                     help="save tilt, null-control torque and thrust estimates against time")
    two.set_defaults(func=_cmd_analyze_two_stage)
    com = sub.add_parser(
        "calibrate-com", help="centre-of-mass offset from tilt and force modulated at two "
        "frequencies (paper Fig. 11)",
        description="On the simulated pendulum, modulate the base pitch at f1 and apply a "
        "calibration force at f2 together; the displacement ASD has a line at each. Their "
        "amplitude ratio, scaled by the known force, arm and mass (and the pendulum's response "
        "ratio |H(f2)/H(f1)|), gives the centre-of-mass offset l_cm = (A1/A2) F L / (M g "
        "sin(tilt)) |H(f2)/H(f1)|, and the counterweight position l_cm2 = l_cm (m1 + m2) / m2. "
        "Runs once per counterweight position and prints true against recovered.",
        epilog="Example: leveler calibrate-com --plot fig11.png. Units are SI; the table "
        "shows mm, um and um/rtHz.")
    com.add_argument("--counterweight-offsets-m", type=float, nargs="+",
                     default=[1e-3, 2e-3, 3e-3, 4e-3, 5e-3], metavar="L",
                     help="counterweight distances from the axis [m] (default: 1..5 mm, the "
                     "paper's)")
    com.add_argument("--tilt-amplitude-rad", type=float, default=25e-6,
                     help="pitch modulation amplitude [rad] (default: %(default)g)")
    com.add_argument("--tilt-frequency-hz", type=float, default=0.1,
                     help="pitch modulation frequency f1 [Hz] (default: %(default)g)")
    com.add_argument("--force-amplitude-n", type=float, default=1e-6,
                     help="calibration force amplitude [N] (default: %(default)g)")
    com.add_argument("--force-frequency-hz", type=float, default=0.11,
                     help="calibration force frequency f2 [Hz] (default: %(default)g)")
    com.add_argument("--duration-s", type=float, default=4000.0,
                     help="length of each run [s] (default: %(default)g)")
    com.add_argument("--fs-hz", type=float, default=5.0,
                     help="sample rate [Hz] (default: %(default)g)")
    com.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default: 0)")
    com.add_argument("--json", action="store_true", help="print one JSON object")
    com.add_argument("--plot", default=None, metavar="FILE.png",
                     help="save the displacement ASDs, one per counterweight position")
    com.set_defaults(func=_cmd_calibrate_com)
    _add_control_commands(sub)
    return parser


#: what a shell reports for a command killed by SIGPIPE (`yes | head` gives it to `yes`)
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE


def _run(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ConfigError, LogError, ClientError, ControlError) as exc:
        print(f"leveler {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"leveler {args.command}: interrupted", file=sys.stderr)
        return 130


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Output into a pipe that closed early (`leveler status | head -3`)
    ends it quietly, as SIGPIPE ends other tools: no traceback, exit 141."""
    try:
        try:
            return _run(argv)
        finally:  # here rather than at exit, where a closed pipe can only be complained of
            sys.stdout.flush()
    except BrokenPipeError:
        with contextlib.suppress(OSError):  # nothing more may reach the closed pipe
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


if __name__ == "__main__":
    sys.exit(main())
