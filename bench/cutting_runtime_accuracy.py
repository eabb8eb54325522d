"""The runtime's scalpel against the full-order model with the same cut meshed explicitly.

    python bench/cutting_runtime_accuracy.py out/cornea-soft.h5 [--depth 0.2] [--out DIR]
        [--interpolation NAME] [--untrained]

Serial. The artifact needs a cuttable region and force-controlled (soft-tip)
training on a generated cornea mesh (any refinement). The scalpel presses at the
trained position nearest the region's centre (``--untrained``: at the surface vertex
nearest the centroid of the sample triangle nearest it, where the rendered surface
is interpolated), blade along the circumference, down to ``--depth`` mm: it cuts as the
blade force passes the artifact's cut force. The faces it cut are then cut in
the mesh explicitly (duplicated nodes), and the full-order model (DOLFINx,
Newton) is loaded with the same soft tip and the runtime's force. Reported:
relative L2 differences of the surface displacement (runtime with the cut,
runtime blind to it, full order without the cut, all against the full order
with the cut), the depths, and a picture of both fields.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

import hapticrom.offline  # noqa: F401 - h5py and MPI first
import hapticrom.online as online
from hapticrom.meshes import build
from hapticrom.meshes.cut import cut_mesh, interior_faces
from hapticrom.meshes.msh import write_msh
from hapticrom.offline.config import ProblemConfig
from hapticrom.offline.fe.dofs import CanonicalOrder
from hapticrom.offline.fe.fullorder import FullOrderModel
from hapticrom.offline.studies.cutting import draw_magnitude
from hapticrom.online.simulator import default_interpolation


def full_order_surface(mesh_file, campaign: dict, point, force, steps: int = 5):
    """Surface-vertex displacement (canonical node order) and depth of a soft-tip solve."""
    from mpi4py import MPI

    config = ProblemConfig.from_dict({
        "mesh": {"file": str(mesh_file)},
        "material": campaign["material"],
        "discretisation": campaign.get("discretisation", {}),
        "load": {"mode": "force", "contact_point": list(point), "force": list(force),
                 "contact_radius": campaign["load"].get("contact_radius", 0.5), "steps": steps},
        "solver": campaign.get("solver", {}),
        "output": {"xdmf": False},
    })  # fmt: skip
    fom = FullOrderModel(config, MPI.COMM_SELF, verbose=False)
    result = fom.solve()
    u = CanonicalOrder(fom.model.V).gather(fom.model.u.x.array).reshape(-1, 3)
    direction = -np.asarray(force) / np.linalg.norm(force)
    return u, float(result.displacement[-1] @ -direction)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--depth", type=float, default=0.2, help="indentation, mm")
    parser.add_argument("--out", default="out/cutting-runtime")
    parser.add_argument(
        "--slide",
        type=int,
        default=0,
        help="then lift and press again this many cells along the blade on either side, one "
        "cell at a time, and back at the start (a longer cut, compared there)",
    )
    parser.add_argument("--layers", type=int, help="cell rings of the cut patch (the artifact's)")
    parser.add_argument("--interpolation", help="the rendered surface (default: the model's)")
    parser.add_argument(
        "--untrained", action="store_true", help="press between samples, not at the nearest one"
    )
    args = parser.parse_args()
    model = online.load(args.model)
    if args.layers:
        model.artifact.group_attrs["cutting"]["patch_layers"] = args.layers
    if model.cut_region is None or model.artifact.attrs is None:
        raise SystemExit(f"{args.model} has no cuttable region")
    campaign = model.artifact.attrs["campaign"]
    if campaign["load"]["mode"] != "force":
        raise SystemExit("this comparison needs a soft-tip (force-controlled) model")
    centre = np.asarray(model.artifact.group_attrs["cutting"]["centre"], dtype=float)
    point = _press_point(model, centre, args.untrained)
    radial = point - [0.0, 0.0, point[2]]
    blade = np.cross([0.0, 0.0, 1.0], radial / np.linalg.norm(radial))
    interpolation = args.interpolation or default_interpolation(model)
    sim, blind = model.simulator(interpolation), model.simulator(interpolation)
    print(
        f"{interpolation} surface, pressed at {np.round(point, 3).tolist()} mm "
        f"({'between samples' if args.untrained else 'a training position'})"
    )
    edges = model.vertices[model.triangles[:, 1]] - model.vertices[model.triangles[:, 0]]
    cell = float(np.median(np.linalg.norm(edges, axis=1)))
    path = [0, *range(-args.slide, args.slide + 1), 0] if args.slide else [0]
    for k in path:
        # On the surface: the vertex nearest the point moved k cells along the blade.
        target = point + k * cell * blade
        at = model.vertices[np.argmin(np.linalg.norm(model.vertices - target, axis=1))]
        sim.scalpel(at if k else point, blade)
        n = sim.contact_normal.copy()
        for depth in np.linspace(0.0, args.depth, 41)[1:]:
            force = sim.step_displacement(-depth * n).copy()
    blind.set_contact(point)
    blind_force = blind.step_displacement(-args.depth * n).copy()
    if not sim.cut_events:
        raise SystemExit("the scalpel did not cut: press deeper or lower the cut force")
    u_runtime = sim.surface_displacement(np.zeros_like(model.vertices)).copy()
    u_blind = blind.surface_displacement(np.zeros_like(model.vertices)).copy()

    # The same faces cut in the mesh file.
    nodes = np.asarray(model.artifact["cutting"]["nodes"])
    keys = {tuple(sorted(nodes[list(f)])) for f in sim.cutting.cuts.topology.cut_faces}
    mesh_name = campaign["mesh"]["file"]
    intact = _generated_cornea(model)
    faces, _ = interior_faces(intact.cells)
    chosen = [i for i, f in enumerate(faces) if tuple(sorted(f)) in keys]
    cut, origin = cut_mesh(intact, np.array(chosen))
    surface = np.asarray(model.artifact["surface"]["nodes"])
    work = Path(tempfile.mkdtemp(prefix="hapticrom-cut-"))
    files = {}
    for name, m in (("intact", intact), ("cut", cut)):
        files[name] = write_msh(work / f"{name}.msh", m.nodes, m.cells, m.facet_groups,
                                m.sidecar())  # fmt: skip
    push = -np.linalg.norm(force) * n  # the runtime's force, into the tissue
    u_cut, depth_cut = full_order_surface(files["cut"], campaign, point, push)
    u_intact, depth_intact = full_order_surface(files["intact"], campaign, point, push)
    reference = u_cut[surface]
    # The haptic question: at the runtime's depth, which force does the full order need?
    f_lo, d_lo = np.linalg.norm(push), depth_cut
    f_hi = f_lo * args.depth / d_lo
    for _ in range(4):  # secant on the force
        u_equal, d_hi = full_order_surface(files["cut"], campaign, point, -f_hi * n)
        if abs(d_hi - args.depth) <= 1e-4 * args.depth:
            break
        f_lo, d_lo, f_hi = f_hi, d_hi, f_hi + (args.depth - d_hi) * (f_hi - f_lo) / (d_hi - d_lo)
    print(f"at the depth {args.depth} mm: runtime {np.linalg.norm(force):.5f} N, full order with "
          f"the cut {f_hi:.5f} N ({100 * (np.linalg.norm(force) / f_hi - 1):+.1f} %); blind "
          f"runtime {np.linalg.norm(blind_force):.5f} N "
          f"({100 * (np.linalg.norm(blind_force) / f_hi - 1):+.1f} %)")  # fmt: skip

    def error(u):
        return float(np.linalg.norm(u - reference) / np.linalg.norm(reference))

    added = len(cut.nodes) - len(intact.nodes)
    print(f"mesh {mesh_name}: {len(chosen)} faces cut by the runtime, {added} duplicated nodes")
    print(f"runtime: depth {args.depth:.3f} mm, force {np.linalg.norm(force):.5f} N with the cut "
          f"({np.linalg.norm(blind_force):.5f} N blind to it)")  # fmt: skip
    print(f"full order with that force: depth {depth_cut:.4f} mm cut, {depth_intact:.4f} mm intact")
    print("at equal force, relative L2 of the surface displacement against the full order with "
          "the cut:")  # fmt: skip
    print(f"  runtime with the cut      {100 * error(u_runtime):6.2f} %")
    print(f"  runtime blind to the cut  {100 * error(u_blind):6.2f} %")
    print(f"  full order without it     {100 * error(u_intact[surface]):6.2f} %  (the cut)")
    reference = u_equal[surface]
    print(f"at equal depth ({args.depth} mm), against the full order with the cut:")
    print(f"  runtime with the cut      {100 * error(u_runtime):6.2f} %")
    print(f"  runtime blind to the cut  {100 * error(u_blind):6.2f} %")
    # The cut's own field: runtime (with the cut - blind, at the same force) against the full
    # order (cut - intact, at the same force).
    same_force = model.simulator(interpolation)
    same_force.set_contact(point)
    same_force.step_force(push)
    u_blind_f = same_force.surface_displacement(np.zeros_like(model.vertices)).copy()
    delta_full = u_cut[surface] - u_intact[surface]
    delta_runtime = u_runtime - u_blind_f
    print(
        f"the cut's own field (cut - intact at {np.linalg.norm(push):.5f} N): runtime "
        f"{np.linalg.norm(delta_runtime):.4f} mm, full order {np.linalg.norm(delta_full):.4f} mm "
        "(surface l2), relative difference "
        f"{np.linalg.norm(delta_runtime - delta_full) / np.linalg.norm(delta_full):.1%}"
    )
    # The runtime's softening is a linear (reference tangent) estimate: compare it with the
    # full order's in the linear range, same tool centre and direction.
    scalpel = sim.cutting
    vertex = scalpel.vertex
    tiny = 1e-6 * scalpel.normals[vertex]  # N, into the tissue
    centre = model.vertices[vertex]
    _, d_cut = full_order_surface(files["cut"], campaign, centre, -tiny, steps=1)
    _, d_intact = full_order_surface(files["intact"], campaign, centre, -tiny, steps=1)
    nonlinear = f_hi / np.linalg.norm(blind_force)
    print(f"cut / intact contact stiffness, linear range: runtime {sim.cut_stiffness_ratio:.4f}, "
          f"full order {d_intact / d_cut:.4f}; at {args.depth} mm: full order "
          f"{nonlinear:.4f} (against the blind runtime's force)")  # fmt: skip
    _picture(Path(args.out), model, u_runtime, reference, point)


def _press_point(model, centre, untrained: bool) -> np.ndarray:
    """The training position nearest ``centre``, or (``untrained``) the surface vertex
    nearest it that is inside the trained region and not a training position."""
    if not untrained:
        return model.sample_points[np.argmin(np.linalg.norm(model.sample_points - centre, axis=1))]
    gap = np.min(np.linalg.norm(model.vertices[:, None] - model.sample_points[None], axis=2), 1)
    candidates = np.flatnonzero(model.inside_trained_region(model.vertices) & (gap > 1e-9))
    if len(candidates) == 0:
        raise SystemExit("no surface vertex of the trained region is untrained")
    nearest = np.argmin(np.linalg.norm(model.vertices[candidates] - centre, axis=1))
    return model.vertices[candidates[nearest]]


def _generated_cornea(model):
    """The generated cornea mesh (of any refinement) the model was trained on."""
    from hapticrom.meshes import REFINEMENTS
    from hapticrom.offline.cutting.export import read_mesh_arrays

    trained_nodes, _, _ = read_mesh_arrays(model.artifact.group_attrs["model"]["mesh_file"])
    for refinement in REFINEMENTS:
        mesh = build("cornea", refinement)
        if mesh.nodes.shape == trained_nodes.shape and np.allclose(mesh.nodes, trained_nodes):
            return mesh
    raise SystemExit("the model was not trained on a generated cornea mesh")


def _picture(out: Path, model, u_runtime, u_reference, point) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    x, tri = model.vertices, model.triangles
    near = np.linalg.norm(x[tri].mean(axis=1)[:, :2] - point[:2], axis=1) < 1.5
    vmax = max(np.linalg.norm(u_runtime, axis=1).max(), np.linalg.norm(u_reference, axis=1).max())
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    fields = (("runtime, scalpel cut", u_runtime), ("full order, cut meshed", u_reference))
    for ax, (title, u) in zip(axes, fields, strict=True):
        draw_magnitude(fig, ax, x, tri[near], u, point, 1.6, vmax, title)
    fig.tight_layout()
    fig.savefig(out / "runtime-cut-vs-full-order.png", dpi=110)
    plt.close(fig)
    print(f"wrote {out / 'runtime-cut-vs-full-order.png'}")


if __name__ == "__main__":
    main()
