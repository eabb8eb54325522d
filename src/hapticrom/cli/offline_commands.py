"""The offline commands (``mesh``, ``solve``, ``campaign``, ``reduce``, ``train``, ``anm``,
``accuracy``, ``physics``): their parsers and what they do. They need the ``offline`` extra and run
under ``mpirun -n N``; all but ``mesh`` take PETSc options at the end of the line."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

from hapticrom.cli.args import float_in, int_in, model_argument, new_command, number_option
from hapticrom.cli.console import log, rank
from hapticrom.cli.outputs import check_campaign_dir, check_out_dir, check_out_file
from hapticrom.cli.petsc import offline_command
from hapticrom.shared.errors import HapticromError

# Held-out positions of `hapticrom accuracy`: each is a full-order solve (minutes on the
# default cornea).
DEFAULT_HELD_OUT = 8
MAX_HELD_OUT = 1000
MAX_ANM_ORDER = 15  # as hapticrom.offline.reduce.anm.ANMOptions checks

# What each command does, in one line (hapticrom --help).
HELP = {
    "mesh": "generate a built-in organ mesh, or import your own (gmsh .msh + .json) [offline]",
    "solve": "full-order nonlinear solve of a TOML configuration [offline]",
    "campaign": "solve a training campaign into a snapshot directory [offline]",
    "reduce": "POD and reduced operators of a campaign [offline]",
    "train": "campaign + reduce in one go [offline]",
    "anm": "POD-ANM of one problem against full Newton: curves, tables [offline]",
    "accuracy": "the reduced model against full-order solves at held-out positions [offline]",
    "physics": "hyper-reduced physics of regions of a model (two tools, holders, pinches, "
    "oblique presses) [offline]",
}


# -- mesh ------------------------------------------------------------------------------------
def mesh_parameters(items: list[str] | None) -> dict[str, int | float | str]:
    """``--set key=value`` items as generator keyword arguments (numbers where they parse)."""
    params: dict[str, int | float | str] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise HapticromError(f"--set expects key=value, got {item!r}")
        for kind in (int, float, str):
            try:
                params[key] = kind(value)
                break
            except ValueError:
                continue
    return params


@offline_command(petsc=False)
def cmd_mesh(args, petsc) -> int:
    """Generate an organ mesh and its JSON sidecar, or import one (rank 0 only)."""
    if args.name == "import":
        return import_organ_mesh(args)
    from hapticrom.meshes import generate

    refuse_options(args, "--rules", "--scale", what=f"mesh {args.name}", reason="of mesh import")
    if args.input is not None:
        raise HapticromError(f"mesh {args.name} takes no INPUT {args.input!r} (mesh import does)")
    params = mesh_parameters(args.set)
    incision = None
    if args.limbal_incision:
        from hapticrom.meshes.cut import LimbalArc

        incision = LimbalArc(*args.limbal_incision)
    out = Path(args.out) if args.out else Path("meshes") / f"{args.name}.msh"
    check_out_file(out, f"mesh --out {out}", make_parents=True)
    if rank() == 0:
        refinement = args.refinement or "default"
        info = generate(args.name, out, refinement=refinement, incision=incision, **params)
        counts = info["counts"]
        log.info(
            f"wrote {out} ({info['cell_type']}, {counts['nodes']} nodes, {counts['cells']} "
            f"cells, units mm) and {out.with_suffix('.json')}"
        )
    return 0


def refuse_options(args, *options: str, what: str, reason: str) -> None:
    """HapticromError if any of ``options`` (``--name``) was given: they are ``reason``."""
    given = [o for o in options if getattr(args, o[2:].replace("-", "_")) is not None]
    if given:
        raise HapticromError(f"{what} takes no {', '.join(given)} (options {reason})")


def import_organ_mesh(args) -> int:
    """``hapticrom mesh import INPUT --out NAME.msh --rules RULES.toml [--scale S]``."""
    from hapticrom.meshes.importer import import_mesh

    refuse_options(
        args,
        "--refinement",
        "--set",
        "--limbal-incision",
        what="mesh import",
        reason="of the built-in organs",
    )
    usage = "hapticrom mesh import INPUT --out NAME.msh --rules RULES.toml [--scale S]"
    if args.input is None:
        raise HapticromError(f"mesh import needs the mesh file INPUT: {usage}")
    if not args.out:
        raise HapticromError(f"mesh import needs --out NAME.msh: {usage}")
    out = check_out_file(args.out, f"mesh --out {args.out}", make_parents=True)
    if rank() == 0:
        report = import_mesh(args.input, out, args.rules, 1.0 if args.scale is None else args.scale)
        for note in report.source.notes:
            log.debug(f"meshio: {note}")
        for line in report.lines():
            log.info(line)
    return 0


def add_mesh(sub) -> None:
    """``hapticrom mesh NAME`` and ``hapticrom mesh import INPUT``."""
    from hapticrom.meshes import MESHES, REFINEMENTS  # pure numpy: gmsh only when meshing

    p = new_command(
        sub,
        "mesh",
        cmd_mesh,
        HELP["mesh"],
        description=(
            "Generate a built-in organ mesh (hapticrom mesh NAME), or import your own "
            "(hapticrom mesh import INPUT --out NAME.msh --rules RULES.toml [--scale S]). "
            "Both write NAME.msh (gmsh MSH 4.1, physical groups tissue, clamped, loadable, "
            "free) and NAME.json (the sidecar), in mm."
        ),
    )
    p.add_argument(
        "name",
        choices=[*MESHES, "import"],
        help="the organ: %(choices)s (import: read INPUT, see below)",
    )
    p.add_argument(
        "input",
        nargs="?",
        metavar="INPUT",
        help="mesh import only: the mesh file (.vtk, .vtu, .msh, .mesh, .inp)",
    )
    p.add_argument(
        "--out",
        metavar="FILE",
        help="output .msh path (default meshes/NAME.msh; required by import)",
    )
    built_in = p.add_argument_group("built-in organs (hapticrom mesh NAME)")
    built_in.add_argument(
        "--refinement",
        choices=REFINEMENTS,
        help="element size: %(choices)s (default: default)",
    )
    built_in.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override a generator parameter"
    )
    built_in.add_argument(
        "--limbal-incision",
        nargs=4,
        type=float,
        metavar=("RADIUS", "START", "END", "DEPTH"),
        help="cornea: mesh a limbal relaxing incision explicitly (mm, degrees, thickness fraction)",
    )
    imported = p.add_argument_group("import (hapticrom mesh import INPUT --out NAME.msh)")
    imported.add_argument(
        "--rules",
        metavar="RULES.toml",
        help="the surface groups: clamped, loadable, the rest free (required; see "
        "examples/mesh-import-rules.toml)",
    )
    imported.add_argument(
        "--scale",
        type=float_in(0.0, 1e9),
        metavar="S",
        help="multiply the coordinates by S to get mm (a mesh in cm: 10; default 1)",
    )


# -- solve -----------------------------------------------------------------------------------
@offline_command()
def cmd_solve(args, petsc) -> int:
    """One full-order nonlinear solve; exit status 1 if no load step converged."""
    from hapticrom.offline.config import ProblemConfig

    config = ProblemConfig.from_toml(args.config)  # fails before MPI/PETSc on a bad file
    out = check_out_dir(args.out, f"solve --out {args.out}")
    petsc.start()
    from hapticrom.offline.fe.fullorder import solve_config

    result = solve_config(config, out_dir=out)
    xdmf = f" and {out / 'fields.xdmf'}" if config.output.xdmf else ""
    log.info(f"wrote {out / 'curve.csv'}, {out / 'sanity.json'}{xdmf}")
    if args.refinement_check:
        from mpi4py import MPI

        from hapticrom.offline.fe.sanity import check_refinement

        check_refinement(config, result, out, MPI.COMM_WORLD)
    return 0 if result.records else 1


def add_solve(sub) -> None:
    """``hapticrom solve CONFIG --out DIR``."""
    p = new_command(sub, "solve", cmd_solve, HELP["solve"])
    p.add_argument("config", help="problem configuration (.toml)")
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="output directory (curve.csv, sanity.json, fields.xdmf)",
    )
    p.add_argument(
        "--refinement-check",
        action="store_true",
        help="solve again on the next finer built-in mesh (in OUT/refinement) and report "
        "the difference at the last step",
    )


# -- campaign, reduce, train -------------------------------------------------------------------
def run_campaign_of(args, config, work: Path) -> bool:
    """Run the campaign ``config`` into ``work`` as the options say; whether a solve failed."""
    from hapticrom.offline.campaign.run import run_campaign

    report = run_campaign(
        config,
        work,
        ranks_per_solve=args.ranks_per_solve,
        restart=args.restart,
        refinement_check=args.refinement_check,
    )
    return bool(report.failed)


@offline_command()
def cmd_campaign(args, petsc) -> int:
    """Solve a training campaign; exit status 1 if a solve failed."""
    from hapticrom.offline.campaign.config import CampaignConfig

    config = CampaignConfig.from_toml(args.campaign)
    out = check_campaign_dir(args.out, f"campaign --out {args.out}", args.restart)
    petsc.start()
    return 1 if run_campaign_of(args, config, out) else 0


@offline_command()
def cmd_reduce(args, petsc) -> int:
    """POD and reduced operators of a solved campaign, written as an artifact."""
    from hapticrom.offline.campaign.store import SnapshotStore

    reduction = None
    if args.campaign:
        from hapticrom.offline.campaign.config import CampaignConfig

        reduction = CampaignConfig.from_toml(args.campaign)
    SnapshotStore(args.campaign_dir).manifest()  # a campaign directory, intact manifest
    out = made_parent(check_out_file(args.out, f"reduce --out {args.out}", make_parents=True))
    petsc.start()
    from hapticrom.offline.reduce.reduction import reduce_campaign

    reduce_campaign(args.campaign_dir, out, reduction=reduction)
    return 0


@offline_command()
def cmd_train(args, petsc) -> int:
    """Campaign (greedy with ``[positions.greedy]``) and reduction in one go; exit status 1
    if a solve failed."""
    from hapticrom.offline.campaign.config import CampaignConfig

    config = CampaignConfig.from_toml(args.campaign)
    out = made_parent(check_out_file(args.out, f"train --out {args.out}", make_parents=True))
    work = args.work or str(out.with_suffix(".campaign"))
    work = check_campaign_dir(work, f"train --work {work}", args.restart)
    petsc.start()
    from hapticrom.offline.reduce.reduction import reduce_campaign

    if config.positions.greedy is not None:
        from hapticrom.offline.campaign.greedy import run_greedy

        report = run_greedy(
            config,
            work,
            ranks_per_solve=args.ranks_per_solve,
            restart=args.restart,
            refinement_check=args.refinement_check,
        )
        failed = bool(report.campaign.failed)
    else:
        failed = run_campaign_of(args, config, work)
    reduce_campaign(work, out, reduction=config)
    return 1 if failed else 0


def made_parent(out):
    """``out`` once its directory exists (a model's folder is made, as ``mesh --out``'s is;
    by every rank: mkdir with exist_ok is safe against the others, and needs no MPI yet)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    return out


def campaign_options(p) -> None:
    """The options ``campaign`` and ``train`` share."""
    p.add_argument("campaign", help="campaign configuration (.toml)")
    number_option(
        p,
        "--ranks-per-solve",
        int_in(1, 1 << 20),
        1,
        "K",
        "ranks cooperating on each solve; the N ranks form N/K groups (default 1)",
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


def add_campaign_reduce_train(sub) -> None:
    """``hapticrom campaign``, ``reduce`` and ``train``."""
    p = new_command(sub, "campaign", cmd_campaign, HELP["campaign"])
    campaign_options(p)
    p.add_argument(
        "--out", required=True, metavar="DIR", help="campaign directory (resumed if it exists)"
    )

    p = new_command(sub, "reduce", cmd_reduce, HELP["reduce"])
    p.add_argument("campaign_dir", help="directory written by `hapticrom campaign`")
    p.add_argument("--out", required=True, metavar="FILE", help="reduced model (.h5)")
    p.add_argument(
        "--campaign",
        metavar="TOML",
        help="the campaign's TOML, to reduce with its current [anm] and [cutting] tables",
    )

    p = new_command(sub, "train", cmd_train, HELP["train"])
    campaign_options(p)
    p.add_argument("--out", required=True, metavar="FILE", help="reduced model (.h5)")
    p.add_argument(
        "--work", metavar="DIR", help="campaign directory (default: OUT with suffix .campaign)"
    )


# -- anm -------------------------------------------------------------------------------------
@offline_command()
def cmd_anm(args, petsc) -> int:
    """POD-ANM of one problem against full Newton: curves and tables."""
    from hapticrom.offline.config import ProblemConfig

    config = ProblemConfig.from_toml(args.config)
    check_out_dir(args.out, f"anm --out {args.out}")
    petsc.start()
    from hapticrom.offline.fe.fullorder import FullOrderModel
    from hapticrom.offline.reduce.anm import ANMOptions
    from hapticrom.offline.reduce.pod import Truncation
    from hapticrom.offline.studies.anm import run_study

    options = ANMOptions(order=args.order, tolerance=args.tolerance)
    fom = FullOrderModel(config, verbose=log.isEnabledFor(logging.INFO))
    run_study(fom, options, Truncation(eigenvalue_ratio=args.eigenvalue_ratio), out_dir=args.out)
    return 0


def add_anm(sub) -> None:
    """``hapticrom anm CONFIG --out DIR``."""
    p = new_command(sub, "anm", cmd_anm, HELP["anm"])
    p.add_argument("config", help="problem configuration (.toml)")
    p.add_argument(
        "--out", required=True, metavar="DIR", help="output directory (anm-*.csv, anm-curves.png)"
    )
    number_option(
        p,
        "--order",
        int_in(1, MAX_ANM_ORDER),
        6,
        "N",
        f"order N of the series (default 6, at most {MAX_ANM_ORDER})",
    )
    number_option(
        p,
        "--tolerance",
        float_in(0.0, 1.0),
        1e-4,
        "TOL",
        "validity tolerance of a section, in (0, 1) (default 1e-4)",
    )
    number_option(
        p,
        "--eigenvalue-ratio",
        float_in(0.0, 1.0),
        1e-8,
        "RATIO",
        "POD truncation: eigenvalues below RATIO x the largest are dropped (default 1e-8)",
    )


# -- accuracy --------------------------------------------------------------------------------
@offline_command()
def cmd_accuracy(args, petsc) -> int:
    """The held-out check; exit status 1 if a held-out solve failed."""
    from hapticrom.offline.accuracy import default_work, plan_held_out

    json_path = check_out_file(args.json, f"accuracy --json {args.json}") if args.json else None
    method, seed = held_out_selection(args)
    plan = plan_held_out(args.model, args.positions, seed, method=method)
    work = args.work or str(default_work(args.model, args.positions, seed, method))
    work = check_campaign_dir(work, f"accuracy --work {work}", args.restart)
    petsc.start()
    from hapticrom.offline.accuracy import run_accuracy

    result = run_accuracy(plan, work, restart=args.restart, json_path=json_path)
    return 1 if result is not None and result.failed else 0


# hapticrom accuracy's seeded selections beside --seed: option -> help (its method is its name)
RANDOM_SELECTIONS = {
    "--outside": "random nodes of the tool's surface group outside the trained region, "
    "reproducible from S: where the runtime clamps the contact to the region's border",
    "--anywhere": "random nodes of the tool's whole surface group, inside the trained region "
    "or not, reproducible from S; the summary gives the force error on each side",
}


def held_out_selection(args) -> tuple[str | None, int | None]:
    """(method, seed) of ``hapticrom accuracy``'s exclusive selection options."""
    for flag in RANDOM_SELECTIONS:
        if (seed := getattr(args, flag[2:])) is not None:
            return flag[2:], seed
    return ("softest" if args.softest else None), args.seed


def accuracy_description() -> str:
    """``hapticrom accuracy --help``: what it measures, the targets, the exit status."""
    from hapticrom.shared.accuracy import FIELD_TARGET, FORCE_TARGETS

    return (
        "Solve the full-order model at held-out tool positions as in the model's training "
        "campaign, and compare the reduced model there at every load step: normal force and "
        f"surface displacement. Targets: force {100 * FORCE_TARGETS['anm']:g} % (POD-ANM) and "
        f"{100 * FORCE_TARGETS['curves']:g} % (curves), surface field {100 * FIELD_TARGET:g} "
        "% (relative L2). Exit status 0 when the check ran, whatever the verdicts; 1 if a "
        "held-out solve failed; 2 for bad input."
    )


def add_accuracy(sub) -> None:
    """``hapticrom accuracy MODEL``."""
    p = new_command(
        sub, "accuracy", cmd_accuracy, HELP["accuracy"], description=accuracy_description()
    )
    model_argument(p)
    number_option(
        p,
        "--positions",
        int_in(1, MAX_HELD_OUT),
        DEFAULT_HELD_OUT,
        "N",
        f"held-out positions, one full-order solve each (default {DEFAULT_HELD_OUT}, "
        f"at most {MAX_HELD_OUT:,})",
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--seed",
        type=int_in(0, 2**32 - 1),
        metavar="S",
        help="random surface nodes of the trained region, reproducible from S "
        "(default: centroids of the sample triangles, snapped to surface nodes)",
    )
    where.add_argument(
        "--softest",
        action="store_true",
        help="the trained region's nodes nearest the softest samples: where a force-"
        "controlled model reaches the trained force deepest and extrapolates in depth",
    )
    for flag, text in RANDOM_SELECTIONS.items():  # seeded like --seed, elsewhere
        where.add_argument(flag, type=int_in(0, 2**32 - 1), metavar="S", help=text)
    p.add_argument(
        "--work",
        metavar="DIR",
        help="held-out campaign directory, resumed if it exists "
        "(default: MODEL with suffix .heldout-N, .heldout-N-seedS, .heldout-N-softest, "
        ".heldout-N-outside-seedS or .heldout-N-anywhere-seedS)",
    )
    p.add_argument("--restart", action="store_true", help="discard what the work directory holds")
    p.add_argument(
        "--json", metavar="FILE", help="also write the errors here (hapticrom report --accuracy)"
    )


# -- physics ---------------------------------------------------------------------------------
def centre_point(text: str) -> tuple[float, float, float]:
    """``--at X,Y,Z``: three finite numbers (mm)."""
    parts = text.split(",")
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and abs(v) <= 1e4 for v in values):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in mm (three finite numbers), got "
                                         f"{text!r}")  # fmt: skip
    return values


def pair_points(text: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``--pair`` or ``--held X1,Y1,Z1,X2,Y2,Z2``: two sites (mm)."""
    parts = text.split(",")
    if len(parts) != 6:
        raise argparse.ArgumentTypeError(f"expected X1,Y1,Z1,X2,Y2,Z2 in mm, got {text!r}")
    first, second = centre_point(",".join(parts[:3])), centre_point(",".join(parts[3:]))
    if first == second:
        raise argparse.ArgumentTypeError(f"the two sites must differ, got {text!r}")
    return first, second


def distances(text: str) -> tuple[float, ...]:
    """``--solves MM,MM``: positive distances (mm)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if not values or not all(math.isfinite(v) and 0 < v <= 1e3 for v in values):
        raise argparse.ArgumentTypeError(f"expected positive distances in mm, got {text!r}")
    return values


@offline_command()
def cmd_physics(args, petsc) -> int:
    """Regions of hyper-reduced physics built from a solved campaign into a model."""
    from mpi4py import MPI

    from hapticrom.offline.campaign.store import SnapshotStore

    if MPI.COMM_WORLD.size > 1:
        raise HapticromError("hapticrom physics runs on one rank (its region solves are "
                             "serial); run it without mpirun")  # fmt: skip
    store = SnapshotStore(args.campaign_dir)
    store.manifest()  # a campaign directory, intact manifest
    out = made_parent(check_out_file(args.out, f"physics --out {args.out}", make_parents=True))
    if out.resolve() == Path(args.model).resolve():
        raise HapticromError(f"physics --out {args.out} is the model itself: write a new file")
    import numpy as np

    from hapticrom.offline.reduce.ecsw_regions import (
        RegionRecipe,
        RegionSite,
        physics_from_campaign,
    )

    sites = [RegionSite(kind, np.array(points, dtype=float).reshape(-1, 3))
             for kind in ("at", "pinch", "oblique", "pair", "held")
             for points in getattr(args, kind) or []]  # fmt: skip
    if not sites:
        raise HapticromError("physics: give a region with --at=X,Y,Z, --pinch=X,Y,Z, "
                             "--oblique=X,Y,Z, --pair=X1,Y1,Z1,X2,Y2,Z2 or "
                             "--held=X1,Y1,Z1,X2,Y2,Z2")  # fmt: skip
    recipe = RegionRecipe(distances=args.solves, per_distance=args.solves_per_distance,
                          state_modes=args.state_modes, pressure_modes=args.pressure_modes,
                          tolerance=args.tolerance, radius=args.radius,
                          second_force=args.second_force, lift=args.lift,
                          between_nodes=args.between_nodes, pinch_force=args.pinch_force,
                          check_tolerance=args.check_tolerance,
                          oblique=0.5 if args.oblique_force is None else args.oblique_force,
                          linear_modes=args.linear_modes,
                          extra_pressure_modes=args.extra_pressure_modes)  # fmt: skip
    if args.lift and not args.held:
        raise HapticromError("physics --lift lifts the holders of --held regions: give --held")
    if args.oblique_force is not None and not args.oblique:
        raise HapticromError("physics --oblique-force is an --oblique region's: give --oblique")
    petsc.start()
    regions = physics_from_campaign(args.model, store, sites, recipe, out)
    log.info(f"wrote {out}: {len(regions)} region(s) of hyper-reduced physics")
    return 0


def add_physics(sub) -> None:
    """``hapticrom physics MODEL CAMPAIGN_DIR --at X,Y,Z --out FILE``."""
    p = new_command(sub, "physics", cmd_physics, HELP["physics"], description=(
        "Build regions of hyper-reduced physics (issue 18: the reduced mixed model solved "
        "online on the few elements ECSW samples: one press, a pinch, an oblique press, two "
        "tools at once, or a press beside a holder) "
        "about points of a model's trained surface, and write them with the model to a "
        "new file (artifact group hyperreduced). Each region takes full-order solves of "
        "the campaign's load path about its centre (on the demo cornea 2 minutes a "
        "single-press region, 3.3 a two-tool one). Load it with "
        "hapticrom.online.load(OUT).physics(region)."))  # fmt: skip
    model_argument(p)
    p.add_argument("campaign_dir", help="the campaign directory the model was reduced from")
    p.add_argument(
        "--at",
        type=centre_point,
        action="append",
        metavar="X,Y,Z",
        help="a region's centre (mm), its solves single presses about it; repeat "
        "for more regions (a negative first coordinate: --at=-1.2,0.5,0.1)",
    )
    p.add_argument(
        "--pinch",
        type=centre_point,
        action="append",
        metavar="X,Y,Z",
        help="a region for a pinch about this point (mm): nine forces at neighbouring "
        "nodes (thesis §3.4.3), its solves pinches about it; after the --at regions",
    )
    p.add_argument(
        "--oblique",
        type=centre_point,
        action="append",
        metavar="X,Y,Z",
        help="a region for presses with a tangential force about this point (mm), its "
        "solves such presses in three directions, its basis the tool's linear responses "
        "too; after the --pinch regions",
    )
    p.add_argument(
        "--pair",
        type=pair_points,
        action="append",
        metavar="X1,Y1,Z1,X2,Y2,Z2",
        help="a region for two tools at these sites (mm), its solves pairs of "
        "presses about them; after the --oblique regions",
    )
    p.add_argument(
        "--held",
        type=pair_points,
        action="append",
        metavar="X1,Y1,Z1,X2,Y2,Z2",
        help="a region where a tool presses about the first site while a holder grips "
        "the second (physics(region, holders=[second])), its solves presses each beside a "
        "holder about the second, its basis the holder's responses; after the --pair regions",
    )
    number_option(
        p,
        "--second-force",
        float_in(0.0, 10.0),
        0.5,
        "F",
        "a --pair region's second tool in its solves, of the campaign's force (default 0.5)",
    )
    number_option(
        p,
        "--pinch-force",
        float_in(0.0, 100.0, "N"),
        0.014,
        "N",
        "each of a --pinch region's nine forces in its solves (default 0.014 N, the thesis')",
    )
    number_option(
        p,
        "--oblique-force",
        float_in(0.0, 10.0),
        None,
        "F",
        "an --oblique region's tangential force in its solves, of the campaign's (default "
        "0.5: 27 degrees off a campaign's normal press)",
    )
    number_option(
        p,
        "--linear-modes",
        int_in(1, 1000),
        60,
        "N",
        "an --oblique region's modes of the tool's linear responses at its loadable "
        "vertices (default 60)",
    )
    number_option(
        p,
        "--lift",
        float_in(0.0, 10.0, "mm"),
        0.0,
        "MM",
        "--held regions: their solves also lift each holder this far against the "
        "campaign's direction (out of the surface for 'normal'), nothing pressing: "
        "grasp-and-lift (omit for none)",
    )
    p.add_argument("--out", required=True, metavar="FILE", help="the model with its physics")
    number_option(
        p,
        "--radius",
        float_in(1e-3, 1e3, "mm"),
        1.0,
        "MM",
        "how far from its centre a region's tools may press (default 1 mm)",
    )
    number_option(
        p,
        "--tolerance",
        float_in(1e-6, 0.5),
        0.004,
        "T",
        "ECSW's tolerance (default 0.004: the two-tool target, README)",
    )
    number_option(
        p,
        "--check-tolerance",
        float_in(0.0, 0.5, low_inclusive=True),
        None,
        "T",
        "ECSW's tolerance of each region's check sample, the runtime's error indicator "
        "(trained apart from the model's sample; below --tolerance; 0: none; default a "
        "quarter of --tolerance)",
    )
    p.add_argument("--solves", type=distances, default=(0.25, 0.5), metavar="MM,MM",
                   help="distances of a region's full-order solves from its centre "
                   "(default 0.25,0.5)")  # fmt: skip
    p.add_argument("--between-nodes", action="store_true",
                   help="a region's solves may also centre the tool on the midpoints of the "
                   "loadable surface's edges: solves closer than a coarse mesh's nodes "
                   "(--solves distances under the nodes' spacing)")  # fmt: skip
    number_option(
        p,
        "--solves-per-distance",
        int_in(1, 64),
        3,
        "N",
        "full-order solves at each distance (default 3)",
    )
    number_option(
        p,
        "--state-modes",
        int_in(1, 1000),
        30,
        "N",
        "displacement modes of the solves' states (default 30)",
    )
    number_option(
        p,
        "--pressure-modes",
        int_in(1, 1000),
        20,
        "N",
        "pressure modes (default 20; each adds a supremizer mode)",
    )
    number_option(
        p,
        "--extra-pressure-modes",
        int_in(0, 1000),
        10,
        "N",
        "up to this many pressure modes more for --held and --oblique regions, whose bases "
        "carry extra displacement modes (default 10)",
    )


def add_offline_commands(sub) -> None:
    """Every offline command, in the order of the pipeline."""
    for add in (add_mesh, add_solve, add_campaign_reduce_train, add_anm, add_accuracy,
                add_physics):  # fmt: skip
        add(sub)
