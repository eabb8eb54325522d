"""A random walk of the tool tip through ``step_position``: no pop-through, no NaN, bounded
force jumps, and a state that recovers (issue "device in, force out").

    python bench/proxy_walk.py out/cornea-soft.h5 [--steps 1000000] [--seed 1] [--friction 0.4,0.25]

The tip starts inside the organ (under the centre of the trained region), takes
Gaussian steps of 0.02 mm (20 mm/s at 1 kHz) in a box 2 mm larger than the organ,
and every 1,000 steps jumps anywhere in the box in one tick (leaving, re-entering,
crossing the organ). Checked at every step:

- forces finite;
- in contact, the proxy on the near side of the surface: above the contact point
  along the contact normal (a proxy that popped through a thin organ would be below);
- the force's change per tick at most 2 k_max times the tip's move, k_max the
  steepest slope of the samples' force curves (the normal's turn as the proxy slides
  adds a little to k |d depth|), while the depth stays within twice the trained
  depth. Deeper, the tip nears the surface's centre of curvature, where the nearest
  point of the surface (and the force's direction) turns fast: reported, not bounded.
  With friction the bound is 2 k_max (1 + mu_s) times the move plus (mu_s - mu_d) |F|:
  where the proxy breaks away the tangential force drops from the static cone to the
  dynamic one in one tick, however small the move (Coulomb's law); and at every step in
  contact |F_t| <= mu_s F_n (stuck) or = mu_d F_n (slipping);
- at the end, lifted and pressed again, the same force as a fresh simulator's.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import hapticrom.online as online


def walk(model, steps: int, seed: int, friction: tuple = ()) -> dict:
    sim, rng = model.simulator(), np.random.default_rng(seed)
    if friction:
        sim.set_friction(*friction)
    mu_s, mu_d, _ = sim.friction
    lo, hi = model.vertices.min(axis=0) - 2.0, model.vertices.max(axis=0) + 2.0
    centre = model.sample_points[int(np.argmin(np.linalg.norm(model.plan_points, axis=1)))]
    normal = model.sample_normals[int(np.argmin(np.linalg.norm(model.plan_points, axis=1)))]
    tip = centre - 0.2 * normal  # inside
    k_max = float(np.max(model.stiffness))
    previous_force, previous_tip = np.zeros(3), tip.copy()
    counts = {"steps": steps, "in_contact": 0, "not_finite": 0, "far_side": 0, "saturated": 0,
              "contacts_started": 0, "slipping": 0, "friction_law_broken": 0}  # fmt: skip
    worst_ratio, deep_ratio, touching, depth = 0.0, 0.0, False, 0.0
    shallow = 2.0 * model.trained_depth
    t0 = time.perf_counter()
    for i in range(steps):
        if i % 1000 == 999:
            tip = rng.uniform(lo, hi)
        else:
            tip = np.clip(tip + rng.normal(0.0, 0.02, 3), lo, hi)
        force = sim.step_position(tip)
        if not np.all(np.isfinite(force)):
            counts["not_finite"] += 1
            continue
        if sim.in_contact:
            counts["in_contact"] += 1
            counts["contacts_started"] += not touching
            counts["saturated"] += sim.saturated
            if (sim.proxy - sim.contact_point) @ sim.contact_normal <= 0.0:
                counts["far_side"] += 1
            counts["slipping"] += sim.slipping
            counts["friction_law_broken"] += not _obeys_coulomb(sim, force, mu_s, mu_d)
        touching = sim.in_contact
        move = np.linalg.norm(tip - previous_tip)
        if move > 0:
            breakaway = (mu_s - mu_d) * np.linalg.norm(previous_force)
            ratio = max(np.linalg.norm(force - previous_force) - breakaway, 0.0) / move
            ratio /= 1.0 + mu_s
            if max(depth, sim.depth) <= shallow:
                worst_ratio = max(worst_ratio, ratio)
            else:
                deep_ratio = max(deep_ratio, ratio)
        depth = sim.depth
        previous_force[:], previous_tip[:] = force, tip
    seconds = time.perf_counter() - t0
    return {
        **counts,
        "seconds": seconds,
        "k_max_n_per_mm": k_max,
        "worst_force_jump_per_mm": worst_ratio,
        "worst_deep_force_jump_per_mm": deep_ratio,
        "recovers": _recovers(model, sim, centre, normal, friction),
    }


def _obeys_coulomb(sim, force, mu_s: float, mu_d: float) -> bool:
    """|F_t| <= mu_s F_n stuck, = mu_d F_n slipping (to round-off); no F_t without friction."""
    m = np.asarray(sim.contact_normal)
    fn = force @ m
    ft = np.linalg.norm(force - fn * m)
    if sim.slipping:
        return abs(ft - mu_d * fn) <= 1e-9 * fn
    return ft <= mu_s * fn + 1e-12 * abs(fn) + 1e-18


def _recovers(model, sim, centre, normal, friction) -> bool:
    """Lifted and pressed again: the same force as a fresh simulator's (to round-off)."""
    fresh = model.simulator()
    if friction:
        fresh.set_friction(*friction)
    press = centre + (sim.tool_radius - 0.5 * model.trained_depth) * normal
    forces = []
    for s in (sim, fresh):
        s.step_position(centre + 3.0 * normal)
        s.step_position(press)
        forces.append(s.step_position(press).copy())
    return bool(np.allclose(forces[0], forces[1], rtol=1e-12, atol=1e-15) and forces[0].any())


RUBBING = " (less the breakaway, over 1 + mu_s)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--friction", default="", metavar="MU_S[,MU_D]",
                        help="Coulomb friction (default frictionless)")  # fmt: skip
    args = parser.parse_args()
    friction = tuple(float(v) for v in args.friction.split(",")) if args.friction else ()
    r = walk(online.load(args.model), args.steps, args.seed, friction)
    print(f"{r['steps']:,} steps in {r['seconds']:.1f} s: {r['in_contact']:,} in contact "
          f"({r['contacts_started']:,} contacts), {r['saturated']:,} held at the displacement "
          f"limit")  # fmt: skip
    print(f"not finite: {r['not_finite']}; proxy on the far side: {r['far_side']}")
    if friction:
        print(f"friction {friction}: {r['slipping']:,} steps slipping; Coulomb's law broken at "
              f"{r['friction_law_broken']} steps")  # fmt: skip
    print(
        f"worst force change per mm of tip move{RUBBING if friction else ''}: "
        f"{r['worst_force_jump_per_mm']:.4g} N/mm "
        f"within twice the trained depth (bound 2 k_max = {2 * r['k_max_n_per_mm']:.4g} "
        f"N/mm); deeper: {r['worst_deep_force_jump_per_mm']:.4g} N/mm"
    )
    print(f"recovers (a fresh simulator's force after the walk): {r['recovers']}")
    ok = (r["not_finite"] == 0 and r["far_side"] == 0 and r["recovers"]
          and r["worst_force_jump_per_mm"] <= 2 * r["k_max_n_per_mm"]
          and r["friction_law_broken"] == 0)  # fmt: skip
    print("verdict:", "met" if ok else "MISSED")


if __name__ == "__main__":
    main()
