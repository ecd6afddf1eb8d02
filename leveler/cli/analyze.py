"""`leveler analyze`: the paper's torsion-pendulum analyses, a subcommand each."""

from __future__ import annotations

import argparse

from leveler.cli import analyze_stiffness, analyze_two_stage


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """`analyze` and its subcommands, each of which brings its own parser and run(args)."""
    p = sub.add_parser(
        "analyze", help="the paper's torsion-pendulum analyses on the simulator or a "
        "recording (stiffness, two-stage)", description="Torsion-pendulum (thrust stand) "
        "analyses from the paper, each a subcommand; stiffness also on a recording (LOG). "
        "The pendulum obeys J theta'' + lambda theta' + K0 theta "
        "= F L + M g sin(pitch) l_cm,y + M g sin(roll) l_cm,x (leveler.sim.torsion).")
    asub = p.add_subparsers(dest="analyze_command", required=True, metavar="ANALYSIS")
    for analysis in (analyze_stiffness, analyze_two_stage):
        analysis.add_parser(asub)
