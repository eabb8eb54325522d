"""The ``hapticrom`` command line.

Offline commands (mesh, solve, campaign, reduce, train, anm, accuracy) need the
``offline`` extra and say so when it is missing; they run under ``mpirun -n N``.
PETSc options go at the end, or after ``--``, and reach PETSc unchanged::

    mpirun -n 2 hapticrom solve examples/cornea-hgo-indent.toml --out out/cornea \\
        -hapticrom_snes_rtol 1e-10 -hapticrom_snes_monitor

A mistake in the input, in a number or in an output location ends with one
line ``hapticrom: error: ...`` and exit status 2 (argparse's own errors too: no
usage block). Output locations are checked before any expensive work.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from hapticrom import __version__
from hapticrom.shared.errors import HapticromError

EXIT_USAGE = 2
EXIT_MISSING_EXTRA = 3
# Bounds of the online commands' numbers: a servo loop of at most an hour (and
# at most MAX_TICKS ticks, which the loop keeps in memory), bench runs that fit
# in memory (about 150 bytes per timed call).
MAX_RATE_HZ = 100_000.0
MAX_SECONDS = 3600.0
MAX_TICKS = 3_600_000  # an hour at 1 kHz
MAX_TIMED_STEPS = 2_000_000
# Held-out positions of `hapticrom accuracy`: each is a full-order solve (minutes on the
# default cornea).
DEFAULT_HELD_OUT = 8
MAX_HELD_OUT = 1000


class _Parser(argparse.ArgumentParser):
    """argparse that keeps the promise: a mistake is one line ``hapticrom: error: ...``."""

    def error(self, message: str):
        if _rank() == 0:
            command = self.prog.removeprefix("hapticrom").strip()
            where = f"{command}: " if command else ""
            print(f"hapticrom: error: {where}{message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def _rank() -> int:
    """MPI rank from the launcher's environment, without importing mpi4py."""
    for var in ("PMI_RANK", "PMIX_RANK", "OMPI_COMM_WORLD_RANK"):
        if var in os.environ:
            return int(os.environ[var])
    return 0


def _split_petsc_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """Split off PETSc options: everything after ``--``, or from the first ``-name`` on.

    argparse cannot be trusted with PETSc's single-dash long options
    (``-hapticrom_snes_rtol`` would be read as ``-h``), so they never reach it.
    """
    if "--" in argv:
        i = argv.index("--")
        return argv[:i], argv[i + 1 :]
    for i, token in enumerate(argv):
        if token.startswith("-") and not token.startswith("--") and len(token) > 2:
            if _is_number(token):  # a negative value (an angle, a coordinate), not an option
                continue
            return argv[:i], argv[i:]
    return argv, []


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


# -- argument types (argparse turns ArgumentTypeError into one line) ---------------
def _int_in(low: int, high: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must lie in [{low:,}, {high:,}], got {value:,}")
        return value

    return parse


def _float_in(low: float, high: float, unit: str):
    """A finite float in (low, high]."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (math.isfinite(value) and low < value <= high):
            raise argparse.ArgumentTypeError(
                f"must be above {low:g} and at most {high:g} {unit}, got {text}"
            )
        return value

    return parse


# -- output locations, checked before any expensive work ----------------------------
def _check_writable(directory: Path, label: str) -> None:
    """HapticromError unless a file can be created in ``directory`` (a probe, removed)."""
    probe = directory / f".hapticrom-probe-{_rank()}-{os.getpid()}"
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        probe.unlink()
    except OSError as exc:
        raise HapticromError(
            f"{label}: cannot write in {directory} ({exc.strerror or exc})"
        ) from None


def _check_out_file(path: str | Path, label: str, make_parents: bool = False) -> Path:
    """An output file: not a directory, in an existing (or creatable) writable directory."""
    out = Path(path)
    if out.is_dir():
        raise HapticromError(f"{label} is a directory; give a file name, e.g. {out / 'model.h5'}")
    if make_parents:
        _check_ancestor(out.parent, label)
        return out
    if not out.parent.is_dir():
        missing = "is not a directory" if out.parent.exists() else "does not exist"
        raise HapticromError(f"{label}: directory {out.parent} {missing}")
    _check_writable(out.parent, label)
    return out


def _check_out_dir(path: str, label: str) -> Path:
    """An output directory: an existing one, or one that can be created; writable."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise HapticromError(f"{label} exists and is not a directory")
    _check_ancestor(out, label)
    return out


def _check_ancestor(path: Path, label: str) -> None:
    """The nearest existing ancestor of ``path`` (or itself) is a writable directory."""
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise HapticromError(f"{label}: {existing} is not a directory")
    _check_writable(existing, label)


def _check_campaign_dir(path: str, label: str, restart: bool) -> Path:
    """A campaign directory to write: as :func:`_check_out_dir`; a manifest it holds is read."""
    out = _check_out_dir(path, label)
    from hapticrom.offline.campaign.store import SnapshotStore

    store = SnapshotStore(out)
    if store.manifest_path.exists() and not restart:
        store.manifest()  # InputError if damaged: before any solve
    return out


def _init_petsc(petsc_args: list[str]) -> None:
    """Hand PETSc its options before anything imports petsc4py.PETSc."""
    import petsc4py
    from mpi4py import MPI  # noqa: F401 - loads libmpi, which PETSc's library needs

    petsc4py.init([sys.argv[0], *petsc_args])


# -- commands ------------------------------------------------------------------
def cmd_mesh(args, petsc_args) -> int:
    from hapticrom.offline import require_offline

    require_offline()
    from hapticrom.meshes import generate

    params = {}
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise HapticromError(f"--set expects key=value, got {item!r}")
        try:
            params[key] = int(value)
        except ValueError:
            try:
                params[key] = float(value)
            except ValueError:
                params[key] = value
    incision = None
    if args.limbal_incision:
        from hapticrom.meshes.cut import LimbalArc

        incision = LimbalArc(*args.limbal_incision)
    out = Path(args.out) if args.out else Path("meshes") / f"{args.name}.msh"
    _check_out_file(out, f"mesh --out {out}", make_parents=True)
    if _rank() == 0:
        info = generate(args.name, out, refinement=args.refinement, incision=incision, **params)
        counts = info["counts"]
        print(
            f"wrote {out} ({info['cell_type']}, {counts['nodes']} nodes, {counts['cells']} cells, "
            f"units mm) and {out.with_suffix('.json')}"
        )
    return 0


def cmd_solve(args, petsc_args) -> int:
    from hapticrom.offline import require_offline

    require_offline()
    from hapticrom.offline.config import ProblemConfig

    config = ProblemConfig.from_toml(args.config)  # fails before MPI/PETSc on a bad file
    out = _check_out_dir(args.out, f"solve --out {args.out}")
    _init_petsc(petsc_args)
    from hapticrom.offline.fe.fullorder import solve_config

    result = solve_config(config, out_dir=out)
    if _rank() == 0:
        print(
            f"wrote {out / 'curve.csv'}, {out / 'sanity.json'}"
            + (f" and {out / 'fields.xdmf'}" if config.output.xdmf else "")
        )
    if args.refinement_check:
        from mpi4py import MPI

        from hapticrom.offline.fe.sanity import check_refinement

        check_refinement(config, result, out, MPI.COMM_WORLD)
    return 0 if result.records else 1


def _offline(petsc_args):
    """Check the extra, hand PETSc its options, and import the MPI world."""
    from hapticrom.offline import require_offline

    require_offline()
    _init_petsc(petsc_args)


def cmd_campaign(args, petsc_args) -> int:
    from hapticrom.offline import require_offline

    require_offline()
    from hapticrom.offline.campaign.run import CampaignConfig

    config = CampaignConfig.from_toml(args.campaign)
    out = _check_campaign_dir(args.out, f"campaign --out {args.out}", args.restart)
    _init_petsc(petsc_args)
    from hapticrom.offline.campaign.run import run_campaign

    report = run_campaign(
        config,
        out,
        ranks_per_solve=args.ranks_per_solve,
        restart=args.restart,
        refinement_check=args.refinement_check,
    )
    return 1 if report.failed else 0


def cmd_reduce(args, petsc_args) -> int:
    from hapticrom.offline import require_offline

    require_offline()
    from hapticrom.offline.campaign.store import SnapshotStore

    reduction = None
    if args.campaign:
        from hapticrom.offline.campaign.run import CampaignConfig

        reduction = CampaignConfig.from_toml(args.campaign)
    SnapshotStore(args.campaign_dir).manifest()  # a campaign directory, intact manifest
    out = _check_out_file(args.out, f"reduce --out {args.out}")
    _offline(petsc_args)
    from hapticrom.offline.reduce.reduction import reduce_campaign

    reduce_campaign(args.campaign_dir, out, reduction=reduction)
    return 0


def cmd_train(args, petsc_args) -> int:
    from hapticrom.offline import require_offline

    require_offline()
    from hapticrom.offline.campaign.run import CampaignConfig

    config = CampaignConfig.from_toml(args.campaign)
    out = _check_out_file(args.out, f"train --out {args.out}")
    work = args.work or str(out.with_suffix(".campaign"))
    work = _check_campaign_dir(work, f"train --work {work}", args.restart)
    _init_petsc(petsc_args)
    from hapticrom.offline.campaign.run import run_campaign
    from hapticrom.offline.reduce.reduction import reduce_campaign

    report = run_campaign(
        config,
        work,
        ranks_per_solve=args.ranks_per_solve,
        restart=args.restart,
        refinement_check=args.refinement_check,
    )
    reduce_campaign(work, out, reduction=config)
    return 1 if report.failed else 0


def cmd_anm(args, petsc_args) -> int:
    from hapticrom.offline import require_offline

    require_offline()
    from hapticrom.offline.config import ProblemConfig

    config = ProblemConfig.from_toml(args.config)
    _check_out_dir(args.out, f"anm --out {args.out}")
    _init_petsc(petsc_args)
    from hapticrom.offline.fe.fullorder import FullOrderModel
    from hapticrom.offline.reduce.anm import ANMOptions
    from hapticrom.offline.reduce.pod import Truncation
    from hapticrom.offline.studies.anm import run_study

    options = ANMOptions(order=args.order, tolerance=args.tolerance)
    fom = FullOrderModel(config, verbose=not args.quiet)
    run_study(fom, options, Truncation(eigenvalue_ratio=args.eigenvalue_ratio), out_dir=args.out)
    return 0


def cmd_accuracy(args, petsc_args) -> int:
    from hapticrom.offline import require_offline

    require_offline()
    from hapticrom.offline.accuracy import default_work, plan_held_out

    json_path = _check_out_file(args.json, f"accuracy --json {args.json}") if args.json else None
    plan = plan_held_out(args.model, args.positions, args.seed)  # the model, its mesh
    work = args.work or str(default_work(args.model, args.positions, args.seed))
    work = _check_campaign_dir(work, f"accuracy --work {work}", args.restart)
    _init_petsc(petsc_args)
    from hapticrom.offline.accuracy import run_accuracy

    result = run_accuracy(plan, work, restart=args.restart, json_path=json_path)
    return 1 if result is not None and result.failed else 0  # a held-out solve failed


def cmd_play(args, petsc_args) -> int:
    ticks = int(args.rate * args.seconds)
    if not 1 <= ticks <= MAX_TICKS:
        raise HapticromError(
            f"play --rate {args.rate:g} --seconds {args.seconds:g} is {ticks:,} servo ticks; "
            f"give between 1 and {MAX_TICKS:,} (an hour at 1 kHz)"
        )
    from hapticrom.online.play import play

    play(args.model, rate=args.rate, seconds=args.seconds, interpolation=args.interpolation,
         realtime=not args.free_running)  # fmt: skip
    return 0


def cmd_bench(args, petsc_args) -> int:
    import json

    from hapticrom.online.latency import measure, report

    json_path = _check_out_file(args.json, f"bench --json {args.json}") if args.json else None
    result = measure(
        args.model, steps=args.steps, interpolation=args.interpolation, response=args.response
    )
    print(report(result))
    if json_path is not None:
        try:
            json_path.write_text(json.dumps(result, indent=2))
        except OSError as exc:
            raise HapticromError(f"cannot write {json_path}: {exc.strerror or exc}") from None
    return 0


def cmd_report(args, petsc_args) -> int:
    from hapticrom.report import write_report

    _check_out_dir(args.out, f"report --out {args.out}")
    path = write_report(
        args.model, args.out, accuracy=args.accuracy, latency_steps=args.latency_steps
    )
    print(f"wrote {path}")
    return 0


def _accuracy_description() -> str:
    from hapticrom.shared.accuracy import FIELD_TARGET, FORCE_TARGETS

    return (
        "Solve the full-order model at held-out tool positions as in the model's training "
        "campaign, and compare the reduced model there at every load step: normal force and "
        f"surface displacement. Targets: force {100 * FORCE_TARGETS['anm']:g} % (POD-ANM) and "
        f"{100 * FORCE_TARGETS['curves']:g} % (curves), surface field {100 * FIELD_TARGET:g} "
        "% (relative L2). Exit status 0 when the check ran, whatever the verdicts; 1 if a "
        "held-out solve failed; 2 for bad input."
    )


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="hapticrom",
        description="Haptic-rate soft-tissue forces by model order reduction (units: mm, N, MPa).",
    )
    parser.add_argument("--version", action="version", version=f"hapticrom {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("mesh", help="generate an organ mesh (gmsh .msh + .json sidecar) [offline]")
    p.add_argument("name", help="cornea, beam, hemisphere or liver")
    p.add_argument("--out", help="output .msh path (default meshes/NAME.msh)")
    p.add_argument("--refinement", default="default", help="coarse, default or fine")
    p.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override a generator parameter"
    )
    p.add_argument(
        "--limbal-incision",
        nargs=4,
        type=float,
        metavar=("RADIUS", "START", "END", "DEPTH"),
        help="cornea: mesh a limbal relaxing incision explicitly (mm, degrees, thickness fraction)",
    )
    p.set_defaults(func=cmd_mesh)

    p = sub.add_parser(
        "solve", help="full-order nonlinear solve of a TOML configuration [offline, mpirun]"
    )
    p.add_argument("config", help="problem configuration (.toml)")
    p.add_argument(
        "--out", required=True, help="output directory (curve.csv, sanity.json, fields.xdmf)"
    )
    p.add_argument(
        "--refinement-check",
        action="store_true",
        help="solve again on the next finer built-in mesh (in OUT/refinement) and report "
        "the difference at the last step",
    )
    p.set_defaults(func=cmd_solve)

    def campaign_options(p):
        p.add_argument("campaign", help="campaign configuration (.toml)")
        p.add_argument(
            "--ranks-per-solve",
            type=_int_in(1, 1 << 20),
            default=1,
            metavar="K",
            help="ranks cooperating on each solve; the N ranks form N/K groups (default 1)",
        )
        p.add_argument(
            "--restart", action="store_true", help="discard what the directory holds and start over"
        )
        p.add_argument(
            "--refinement-check",
            action="store_true",
            help="afterwards, solve position 0 again on the next finer built-in mesh (in "
            "CAMPAIGN_DIR/refinement) and report the difference (CAMPAIGN_DIR/refinement.json)",
        )

    p = sub.add_parser(
        "campaign", help="solve a training campaign into a snapshot directory [offline, mpirun]"
    )
    campaign_options(p)
    p.add_argument("--out", required=True, help="campaign directory (resumed if it exists)")
    p.set_defaults(func=cmd_campaign)

    p = sub.add_parser("reduce", help="POD and reduced operators of a campaign [offline, mpirun]")
    p.add_argument("campaign_dir", help="directory written by `hapticrom campaign`")
    p.add_argument("--out", required=True, help="reduced model (.h5)")
    p.add_argument(
        "--campaign",
        help="the campaign's TOML, to reduce with its current [anm] and [cutting] tables",
    )
    p.set_defaults(func=cmd_reduce)

    p = sub.add_parser("train", help="campaign + reduce in one go [offline, mpirun]")
    campaign_options(p)
    p.add_argument("--out", required=True, help="reduced model (.h5)")
    p.add_argument("--work", help="campaign directory (default: OUT with suffix .campaign)")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser(
        "anm", help="POD-ANM of one problem against full Newton: curves, tables [offline, mpirun]"
    )
    p.add_argument("config", help="problem configuration (.toml)")
    p.add_argument("--out", required=True, help="output directory (anm-*.csv, anm-curves.png)")
    p.add_argument("--order", type=int, default=6, help="order N of the series (default 6)")
    p.add_argument(
        "--tolerance", type=float, default=1e-4, help="validity tolerance of a section (1e-4)"
    )
    p.add_argument(
        "--eigenvalue-ratio", type=float, default=1e-8, help="POD truncation (default 1e-8)"
    )
    p.add_argument("--quiet", action="store_true", help="do not print the Newton steps")
    p.set_defaults(func=cmd_anm)

    p = sub.add_parser(
        "accuracy",
        help="the reduced model against full-order solves at held-out positions [offline, mpirun]",
        description=_accuracy_description(),
    )
    p.add_argument("model", help="reduced-model artifact (.h5)")
    p.add_argument(
        "--positions",
        type=_int_in(1, MAX_HELD_OUT),
        default=DEFAULT_HELD_OUT,
        metavar="N",
        help=f"held-out positions, one full-order solve each (default {DEFAULT_HELD_OUT}, "
        f"at most {MAX_HELD_OUT:,})",
    )
    p.add_argument(
        "--seed",
        type=_int_in(0, 2**32 - 1),
        metavar="S",
        help="random surface nodes of the trained region, reproducible from S "
        "(default: centroids of the sample triangles, snapped to surface nodes)",
    )
    p.add_argument(
        "--work",
        metavar="DIR",
        help="held-out campaign directory, resumed if it exists "
        "(default: MODEL with suffix .heldout-N or .heldout-N-seedS)",
    )
    p.add_argument("--restart", action="store_true", help="discard what the work directory holds")
    p.add_argument(
        "--json", metavar="FILE", help="also write the errors here (hapticrom report --accuracy)"
    )
    p.set_defaults(func=cmd_accuracy)

    p = sub.add_parser("play", help="drive a scripted tool path through the runtime [online]")
    p.add_argument("model", help="reduced-model artifact (.h5)")
    p.add_argument(
        "--rate",
        type=_float_in(0.0, MAX_RATE_HZ, "Hz"),
        default=1000.0,
        help=f"servo rate, Hz (default 1000, at most {MAX_RATE_HZ:g})",
    )
    p.add_argument(
        "--seconds",
        type=_float_in(0.0, MAX_SECONDS, "s"),
        default=3.0,
        help=f"duration of the tool path, s (default 3, at most {MAX_SECONDS:g}; "
        f"rate x seconds at most {MAX_TICKS:,} ticks)",
    )
    p.add_argument("--interpolation", default="podi", choices=["podi", "grassmann"])
    p.add_argument("--free-running", action="store_true", help="do not pace in real time")
    p.set_defaults(func=cmd_play)

    p = sub.add_parser("bench", help="latency of the runtime's calls [online]")
    p.add_argument("model", help="reduced-model artifact (.h5)")
    p.add_argument(
        "--steps",
        type=_int_in(1, MAX_TIMED_STEPS),
        default=100_000,
        help=f"timed steps (default 100,000, at most {MAX_TIMED_STEPS:,})",
    )
    p.add_argument("--interpolation", default="podi", choices=["podi", "grassmann"])
    p.add_argument(
        "--response",
        choices=["anm", "curves"],
        help="POD-ANM series (default if present) or curves",
    )
    p.add_argument("--json", help="also write the figures here")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("report", help="HTML report on a reduced model: spectra, curves, latency")
    p.add_argument("model", help="reduced-model artifact (.h5)")
    p.add_argument("--out", required=True, help="output directory (report.html and its PNGs)")
    p.add_argument(
        "--accuracy", metavar="JSON", help="held-out errors: hapticrom accuracy MODEL --json JSON"
    )
    p.add_argument(
        "--latency-steps",
        type=_int_in(1, MAX_TIMED_STEPS),
        default=20_000,
        metavar="N",
        help=f"timed steps (20,000, at most {MAX_TIMED_STEPS:,})",
    )
    p.set_defaults(func=cmd_report)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, petsc_args = _split_petsc_args(argv)
    parser = build_parser()
    args = parser.parse_args(ours)
    try:
        return args.func(args, petsc_args)
    except ImportError as exc:
        if "offline" in str(exc) or getattr(exc, "name", "") in (
            "dolfinx",
            "petsc4py",
            "mpi4py",
            "gmsh",
        ):
            if _rank() == 0:
                print(f"hapticrom: error: {exc}", file=sys.stderr)
            return EXIT_MISSING_EXTRA
        raise
    except HapticromError as exc:
        if _rank() == 0:
            print(f"hapticrom: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
