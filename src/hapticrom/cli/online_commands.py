"""The commands that need no finite-element stack (``play``, ``bench``, ``report``, ``export``,
``check``): their parsers and what they do. They take no PETSc options: an option they do
not know, ``-steps 5`` included, is refused."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hapticrom.cli.args import float_in, int_in, model_argument, new_command, number_option
from hapticrom.cli.console import log, result
from hapticrom.cli.outputs import check_out_dir, check_out_file
from hapticrom.shared.errors import HapticromError

# as hapticrom.online.model.INTERPOLATIONS (not imported: the CLI starts without numba)
INTERPOLATIONS = ("transport", "compliance", "podi", "grassmann")
RESPONSES = ("anm", "curves")
# Bounds of the online commands' numbers: a servo loop of at most an hour (and at most
# MAX_TICKS ticks, which the loop keeps in memory), bench runs that fit in memory (about
# 150 bytes per timed call), exports of at most MAX_FRAMES files.
MAX_RATE_HZ = 100_000.0
MAX_SECONDS = 3600.0
MAX_TICKS = 3_600_000  # an hour at 1 kHz
MAX_TIMED_STEPS = 2_000_000
MAX_FRAMES = 10_000  # as hapticrom.export checks

# What each command does, in one line (hapticrom --help).
HELP = {
    "play": "drive a scripted tool path through the runtime [online]",
    "bench": "latency of the runtime's calls [online]",
    "report": "HTML report on a reduced model: spectra, curves, errors, latency [report]",
    "export": "the model's surface and deformed frames as VTU/VTP files for ParaView [online]",
    "check": "check a configuration (.toml) without solving: one line, or the first mistake",
}


# -- play ------------------------------------------------------------------------------------
def cmd_play(args, petsc) -> int:
    """Drive the scripted tool path (or --path) through the runtime; what it does goes to
    the log, the history to --out."""
    ticks = int(args.rate * args.seconds)
    if args.path is None and not 1 <= ticks <= MAX_TICKS:
        raise HapticromError(
            f"play --rate {args.rate:g} --seconds {args.seconds:g} is {ticks:,} servo ticks; "
            f"give between 1 and {MAX_TICKS:,} (an hour at 1 kHz)"
        )
    if args.out is not None:
        check_out_file(args.out + ".csv", f"play --out {args.out}")
    from hapticrom.online.play import play

    play(args.model, rate=args.rate, seconds=args.seconds, interpolation=args.interpolation,
         realtime=not args.free_running, say=log.info, tip_path=args.path,
         out=args.out, friction=args.friction)  # fmt: skip
    return 0


def interpolation_option(p) -> None:
    """``--interpolation``, as ``play`` and ``bench`` take it."""
    p.add_argument(
        "--interpolation",
        default=None,
        choices=INTERPOLATIONS,
        help="of the rendered surface: %(choices)s (default: transport where one plan view "
        "charts the model's samples, else compliance where the model has contact fields "
        "(artifact 2.2), else podi; grassmann needs the model's grassmann group)",
    )


def add_play(sub) -> None:
    """``hapticrom play MODEL``."""
    p = new_command(sub, "play", cmd_play, HELP["play"])
    model_argument(p)
    number_option(
        p,
        "--rate",
        float_in(0.0, MAX_RATE_HZ, "Hz"),
        1000.0,
        "HZ",
        f"servo rate, Hz (default 1000, at most {MAX_RATE_HZ:g})",
    )
    number_option(
        p,
        "--seconds",
        float_in(0.0, MAX_SECONDS, "s"),
        3.0,
        "S",
        f"duration of the tool path, s (default 3, at most {MAX_SECONDS:g}; "
        f"rate x seconds at most {MAX_TICKS:,} ticks)",
    )
    interpolation_option(p)
    p.add_argument("--free-running", action="store_true", help="do not pace in real time")
    p.add_argument(
        "--path",
        metavar="CSV",
        help="the tool tip's centre over time instead of the scripted path: a CSV file with "
        "columns t, x, y, z (s, mm; header line optional); --rate and --seconds then unused",
    )
    p.add_argument(
        "--out",
        metavar="PREFIX",
        help="write the history (tip, force, depth, contact, friction) to PREFIX.csv and a "
        "plot to PREFIX.png (matplotlib)",
    )
    p.add_argument(
        "--friction",
        type=friction_coefficients,
        metavar="MU_S[,MU_D]",
        help="Coulomb friction at the tool: static and dynamic coefficients (dynamic: the "
        "static one if not given; at most 10); default frictionless",
    )


def friction_coefficients(text: str) -> tuple[float, ...]:
    """``--friction``'s one or two numbers (the simulator checks their values)."""
    parts = text.split(",")
    try:
        values = tuple(float(part) for part in parts)
    except ValueError:
        values = ()
    if not 1 <= len(values) <= 2:
        raise argparse.ArgumentTypeError(f"expected MU_S or MU_S,MU_D, got {text!r}")
    return values


# -- bench -----------------------------------------------------------------------------------
def cmd_bench(args, petsc) -> int:
    """Time the runtime's calls; print the table (even with -q), optionally write JSON."""
    from hapticrom.online.latency import measure, report

    json_path = check_out_file(args.json, f"bench --json {args.json}") if args.json else None
    figures = measure(
        args.model, steps=args.steps, interpolation=args.interpolation, response=args.response
    )
    result(report(figures))
    if json_path is not None:
        try:
            json_path.write_text(json.dumps(figures, indent=2))
        except OSError as exc:
            raise HapticromError(f"cannot write {json_path}: {exc.strerror or exc}") from None
        log.info(f"wrote {json_path}")
    return 0


def add_bench(sub) -> None:
    """``hapticrom bench MODEL``."""
    p = new_command(sub, "bench", cmd_bench, HELP["bench"])
    model_argument(p)
    number_option(
        p,
        "--steps",
        int_in(1, MAX_TIMED_STEPS),
        100_000,
        "N",
        f"timed steps (default 100,000, at most {MAX_TIMED_STEPS:,})",
    )
    interpolation_option(p)
    p.add_argument(
        "--response",
        choices=RESPONSES,
        help="the force: %(choices)s (default: the POD-ANM series if the model has them)",
    )
    p.add_argument("--json", metavar="FILE", help="also write the figures here (JSON)")


# -- report ----------------------------------------------------------------------------------
def cmd_report(args, petsc) -> int:
    """Write the HTML report (needs matplotlib: the ``report`` extra)."""
    check_out_dir(args.out, f"report --out {args.out}")
    from hapticrom.report import write_report

    path = write_report(
        args.model,
        args.out,
        accuracy=args.accuracy,
        latency_steps=args.latency_steps,
        held_out_dir=args.held_out,
    )
    log.info(f"wrote {path}")
    return 0


def add_report(sub) -> None:
    """``hapticrom report MODEL --out DIR``."""
    p = new_command(sub, "report", cmd_report, HELP["report"])
    model_argument(p)
    p.add_argument(
        "--out", required=True, metavar="DIR", help="output directory (report.html and its PNGs)"
    )
    p.add_argument(
        "--accuracy", metavar="JSON", help="held-out errors: hapticrom accuracy MODEL --json JSON"
    )
    p.add_argument(
        "--held-out",
        metavar="DIR",
        help="held-out solves of hapticrom accuracy MODEL (MODEL.heldout-8 by default): adds "
        "the rendered surface against the full order at the position where PODI is worst",
    )
    number_option(
        p,
        "--latency-steps",
        int_in(1, MAX_TIMED_STEPS),
        20_000,
        "N",
        f"timed steps (default 20,000, at most {MAX_TIMED_STEPS:,})",
    )


# -- export, check ---------------------------------------------------------------------------
def cmd_export(args, petsc) -> int:
    """Write VTU/VTP files of the model for ParaView; print their paths (even with -q)."""
    out = check_out_dir(args.out, f"export --out {args.out}")
    from hapticrom.export import export_model

    for path in export_model(Path(args.model), out, frames=args.frames, cut=args.cut):
        result(str(path))
    return 0


def cmd_check(args, petsc) -> int:
    """Check a TOML configuration without solving; print its one-line summary."""
    from hapticrom.offline.check import check_config

    result(check_config(Path(args.config)))
    return 0


def add_export_check(sub) -> None:
    """``hapticrom export MODEL --out DIR`` and ``hapticrom check CONFIG``."""
    p = new_command(sub, "export", cmd_export, HELP["export"])
    model_argument(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    number_option(
        p,
        "--frames",
        int_in(1, MAX_FRAMES),
        20,
        "N",
        f"deformed frames of the indentation (default 20, at most {MAX_FRAMES:,})",
    )
    p.add_argument(
        "--cut",
        action="store_true",
        default=True,
        help="also export the scalpel's cut when the model has a cuttable region (default)",
    )
    p.add_argument("--no-cut", dest="cut", action="store_false", help="do not export the cut")

    p = new_command(sub, "check", cmd_check, HELP["check"])
    p.add_argument("config", help="configuration file (.toml)")


def add_online_commands(sub) -> None:
    """Every command that runs without the finite-element stack."""
    for add in (add_play, add_bench, add_report, add_export_check):
        add(sub)
