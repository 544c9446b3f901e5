"""maps: outcome maps: launches per second, memory, cheaper levels and tolerances, adaptive maps
against dense ones. Times: compiled calls.

    python benchmarks/maps.py --cost
    python benchmarks/maps.py --adaptive-agreement   # dense 256^2 maps of four tops: minutes
    python benchmarks/maps.py --adaptive-speed       # dense 512^2 and 1024^2 maps: a quarter of an hour
    python benchmarks/maps.py --adaptive-speed --sizes 256 --big 1000   # minutes
"""

from __future__ import annotations

import math

import _harness as h
import jax
import jax.numpy as jnp
import numpy as np

import tippejax as tj


def second_call(fn):
    fn()
    wall, _, out = h.call(fn)
    return out, wall


def moves(ref, other) -> str:
    diff = ref != other
    out = {}
    for a, b in zip(ref[diff], other[diff]):
        key = f"{tj.OUTCOMES[int(a)]} -> {tj.OUTCOMES[int(b)]}"
        out[key] = out.get(key, 0) + 1
    return ", ".join(f"{k} {v}" for k, v in sorted(out.items(), key=lambda kv: -kv[1])) or "none"


def cost(args):
    """`outcome_map` against a loop of `simulate`; other levels and tolerances against the
    reference map; memory per launch."""
    n_theta, n_spin = (3, 4) if args.smoke else (args.n_theta, args.n_spin)
    theta0, spin = np.linspace(0.02, 1.5, n_theta), np.linspace(10.0, 220.0, n_spin)
    top, t1 = tj.default_top(), 2.0 if args.smoke else args.t1
    n, kw = theta0.size * spin.size, dict(summary=True, throw=False, rtol=1e-6, atol=1e-9)
    maps = {
        label: second_call(lambda k=k: tj.outcome_map(top, theta0, spin, t1=t1, **k))
        for label, k in (
            ("full, rtol 1e-6", dict(model="full")),
            ("full, rtol 1e-9", dict(model="full", rtol=1e-9, atol=1e-12)),
            ("so3, rtol 1e-6", dict(model="so3")),
            ("routhian, rtol 1e-6", dict(model="routhian")),
        )
    }
    ref, t_map = maps["full, rtol 1e-6"]

    def one(a, b):
        return tj.simulate(top, tj.initial_state(top, a, b), t1, **kw).theta

    sample = [
        (a, b) for a in theta0[:: max(1, theta0.size // 4)] for b in spin[:: max(1, spin.size // 4)]
    ]
    loop = jax.jit(one)
    jax.block_until_ready(loop(0.1, 100.0))
    t_loop = sum(h.call(lambda a=a, b=b: loop(a, b))[0] for a, b in sample) / len(sample) * n
    times = {f"loop of jitted tj.simulate ({len(sample)} launches, scaled)": t_loop}
    times |= {f"tj.outcome_map ({label})": wall for label, (_, wall) in maps.items()}
    rows = [f"{k} | {w:.2f} | {n / w:.1f} | {w / t_map:.2f}" for k, w in times.items()]
    out_ref = np.asarray(ref.outcome)
    agree = "; ".join(
        f"{label} {int((np.asarray(om.outcome) != out_ref).sum())} of {n} ({moves(out_ref, np.asarray(om.outcome))})"
        for label, (om, _) in list(maps.items())[1:]
    )
    sizes = {}
    for k in (256, 1024):
        mem = (
            jax.jit(jax.vmap(one))
            .lower(jnp.full(k, 0.1), jnp.full(k, 100.0))
            .compile()
            .memory_analysis()
        )
        sizes[k] = mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes
    h.write(
        "maps.py --cost",
        "Cost of a map, and what a cheaper level or another tolerance changes",
        f"""
{theta0.size} x {spin.size} launches, t1 = {t1:g} s.

{h.table("run | wall s | launches/s | vs outcome_map", rows)}

Outcomes that differ from the reference map: {agree}. Memory per launch: {sizes[256] / 1e6:.2f} MB for 256 launches, {sizes[1024] / 1e6:.2f} MB for 1024: **{(sizes[1024] - sizes[256]) / 768e3:.1f} kB per launch**, whatever t1.
""",
        args,
    )


# --- adaptive maps ---------------------------------------------------------------------------

ADAPTIVE_TOPS = {
    # group: (A/C, eps/R), spin range in units of n_ref (n1, or n2 where n1 is undefined)
    "IIa": ((0.69, 0.38), (0.3, 7.0)),
    "IIb": ((0.9, 0.3), (0.3, 7.0)),
    "III": ((1.6, 0.2), (0.3, 7.0)),
    "Ib": ((0.65, 0.15), (0.5, 12.0)),  # contact loss at its fastest spins
}


def refine_for(n: int) -> int:
    """The levels of `tippejax map --adaptive`: a base grid of about 32 cells per axis."""
    return max(0, round(math.log2(max(n - 1, 1) / 32)))


def distance_to_boundary(dense: np.ndarray) -> np.ndarray:
    """For every point, the chessboard distance (cells) to the nearest point of another outcome
    in the dense map."""
    from scipy.ndimage import distance_transform_cdt

    out = np.zeros(dense.shape, int)
    for code in np.unique(dense):
        same = dense == code
        out[same] = distance_transform_cdt(same, metric="chessboard")[same]
    return out


def agreement(dense, adaptive) -> dict:
    d, a = np.asarray(dense.outcome), np.asarray(adaptive.outcome)
    differ = d != a
    dist = distance_to_boundary(d)
    return dict(
        agree=float(np.mean(~differ)),
        differ=int(differ.sum()),
        worst=int(dist[differ].max()) if differ.any() else 0,
        share=adaptive.share_simulated,
        steps=float(np.sum(np.asarray(adaptive.num_steps)) / np.sum(np.asarray(dense.num_steps))),
    )


def boundary_cells(om) -> str:
    parts = []
    for b in om.boundaries():
        theory = (
            f", {b.distance:.2f} (max {b.distance_max:.1f}) from {b.theory}" if b.theory else ""
        )
        parts.append(
            f"{b.outcomes[0]}/{b.outcomes[1]} {b.cells} cells, D {b.dimension:.2f}{theory}"
        )
    return "; ".join(parts)


def adaptive_agreement(args):
    """Adaptive maps against dense full-model maps of four tops in different groups, on seeded
    random axis ranges: agreement, distance of each disagreement to a true boundary, share
    simulated, boundaries."""
    rng = np.random.default_rng(59)
    n = 17 if args.smoke else args.resolution
    t1 = 2.0 if args.smoke else args.t1
    k = 2 if args.smoke else refine_for(n)  # (the smoke grid is below the base grid's size)
    rows, notes = [], []
    # compile the dense map's chunk program (one chunk of 4096 launches)
    tj.outcome_map(tj.default_top(), **standard_axes(9 if args.smoke else 64), t1=0.01)
    for group, (ratios, (lo, hi)) in list(ADAPTIVE_TOPS.items())[: 1 if args.smoke else None]:
        top = tj.TippeTop.from_ratios(*ratios, m=0.02, R=0.025, mu=0.3)
        th = tj.thresholds(top)
        n_ref = float(th.n1) if np.isfinite(float(th.n1)) else float(th.n2)
        theta = np.sort(rng.uniform([0.02, 1.0], [0.3, 1.5]))
        spin = np.sort(rng.uniform([lo * 0.8, hi * 0.8], [lo * 1.25, hi * 1.25])) * n_ref
        axes = dict(theta0=np.linspace(*theta, n), spin=np.linspace(*spin, n))
        tj.outcome_map(top, **axes, t1=0.01, refine=k)  # compiles the adaptive program
        t_dense, _, dense = h.call(lambda top=top, axes=axes: tj.outcome_map(top, **axes, t1=t1))
        t_adapt, _, adaptive = h.call(
            lambda top=top, axes=axes: tj.outcome_map(top, **axes, t1=t1, refine=k)
        )
        c = agreement(dense, adaptive)
        rows.append(
            f"{group} ({ratios[0]}, {ratios[1]}) | {n} x {n} | {theta[0]:.2f}-{theta[1]:.2f} | {spin[0]:.0f}-{spin[1]:.0f} | "
            f"{100 * c['agree']:.3f}% ({c['differ']}) | {c['worst']} | {100 * c['share']:.2f}% | {c['steps']:.3f} | {t_adapt / t_dense:.3f}"
        )
        notes.append(
            (
                f"- {group}: {boundary_cells(adaptive)}"
                + (f"; refinement stopped in {adaptive.unresolved}" if adaptive.unresolved else "")
            ).rstrip()
        )
    h.write(
        "maps.py --adaptive-agreement",
        "Adaptive maps against dense maps",
        f"""
refine = {k}, t1 = {t1:g} s.

{h.table(["top", "grid", "theta0 (rad)", "spin (rad/s)", "agreement (cells differing)", "worst distance", "simulated", "steps", "wall"], rows)}

Boundaries of the adaptive maps:

{chr(10).join(notes)}

Targets: agreement >= 99.9%, every disagreement within one cell of a true boundary (worst distance <= 1).
""",
        args,
    )


STANDARD_AXES = ((0.02, 1.5), (10.0, 220.0))


def standard_axes(n):
    (a, b), (c, d) = STANDARD_AXES
    return dict(theta0=np.linspace(a, b, n), spin=np.linspace(c, d, n))


def adaptive_speed(args):
    """The standard top's adaptive map against its dense map at 512^2 and 1024^2 (one run of
    each, compiled), and adaptive maps of 1000^2 and 4096^2."""
    top, t1 = tj.default_top(), 2.0 if args.smoke else args.t1
    sizes = (17, 33) if args.smoke else tuple(args.sizes)
    big = (65, 129) if args.smoke else tuple(args.big)
    # compile the dense map's chunk program (one chunk of 4096 launches)
    tj.outcome_map(top, **standard_axes(9 if args.smoke else 64), t1=0.01)
    rows = []
    for n in sizes:
        k = refine_for(n)
        tj.outcome_map(top, **standard_axes(n), t1=0.01, refine=k)  # compiles its program
        t_dense, _, dense = h.call(lambda n=n: tj.outcome_map(top, **standard_axes(n), t1=t1))
        t_adapt, _, adaptive = h.call(
            lambda n=n, k=k: tj.outcome_map(top, **standard_axes(n), t1=t1, refine=k)
        )
        c = agreement(dense, adaptive)
        simulated = f"{int(np.sum(np.asarray(adaptive.simulated)))} ({100 * c['share']:.2f}%)"
        rows.append(
            f"{n} x {n} | {k} | {t_dense:.0f} | {t_adapt:.1f} | {simulated} | **1/{1 / c['share']:.0f}** | **1/{t_dense / t_adapt:.0f}** | "
            f"{100 * c['agree']:.3f}% ({c['differ']}, worst {c['worst']})"
        )
        dimension = boundary_cells(adaptive)
    big_rows = []
    report(args, t1, sizes, (), rows, big_rows, dimension)  # (kept if a large map is stopped)
    for n in big:
        k = refine_for(n)
        tj.outcome_map(top, **standard_axes(n), t1=0.01, refine=k)  # compiles its program
        wall, cpu, om = h.call(
            lambda n=n, k=k: tj.outcome_map(top, **standard_axes(n), t1=t1, refine=k)
        )
        simulated = f"{int(np.sum(np.asarray(om.simulated)))} ({100 * om.share_simulated:.3f}%)"
        big_rows.append(
            f"{n} x {n} | {k} | {wall:.1f} | {cpu:.0f} | {simulated} | {len(om.levels)} | {len(om.unresolved)}"
        )
        report(args, t1, sizes, big[: len(big_rows)], rows, big_rows, dimension)


def report(args, t1, sizes, big, rows, big_rows, dimension):
    """The block of `--adaptive-speed` with the maps run so far."""
    limits = {512: 20, 1024: 50}
    not_run = [n for n in (512, 1024) if n not in sizes] + [n for n in (1000, 4096) if n not in big]
    h.write(
        "maps.py --adaptive-speed",
        "Adaptive maps: cost against the dense map",
        f"""
{h.table(["grid", "refine", "dense wall s", "adaptive wall s", "launches simulated", "simulations", "wall time", "agreement (differing, worst distance)"], rows)}

Targets: at most 1/{limits[512]} of the dense map's simulations and wall time at 512^2, 1/{limits[1024]} at 1024^2. Boundaries of the {sizes[-1]}^2 adaptive map: {dimension}.

{h.table(["adaptive map", "refine", "wall s", "CPU s", "launches simulated", "batched calls", "regions not refined"], big_rows) if big_rows else "No adaptive map of the large sizes was run."}

Targets: 1000^2 within 60 s and 4096^2 within 600 s on 2 CPU cores.{f" **Not run in this run: {', '.join(f'{n}^2' for n in not_run)}** (`--sizes`, `--big`)." if not_run else ""}
""",
        args,
    )


def options(prs):
    prs.add_argument("--n-theta", type=int, default=24)
    prs.add_argument("--n-spin", type=int, default=32)
    prs.add_argument("--t1", type=float, default=20.0)
    prs.add_argument("--resolution", type=int, default=256, help="--adaptive-agreement")
    prs.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=[512, 1024],
        help="--adaptive-speed: grids (points per axis) run dense and adaptive",
    )
    prs.add_argument(
        "--big",
        type=int,
        nargs="*",
        default=[1000, 4096],
        help="--adaptive-speed: grids run adaptive only",
    )


MODES = {
    "cost": (cost, "a map against a loop of simulate; levels, tolerances; memory"),
    "adaptive-agreement": (adaptive_agreement, "adaptive against dense maps of four tops"),
    "adaptive-speed": (adaptive_speed, "adaptive against dense maps: simulations, wall time"),
}

if __name__ == "__main__":
    h.run(MODES, h.parse(__doc__, MODES, options))
