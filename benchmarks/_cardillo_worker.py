"""One run of cardillo's tippe-top example (`benchmarks/real_tops.py --peers`), in cardillo's own
python: `python _cardillo_worker.py CHECKOUT DT T_FINAL OUT.npz` (no tippejax, no jax)."""

import importlib.util
import pathlib
import sys
import time

import numpy as np


def cardillo_worker(checkout, dt, t_final, out):
    """Run cardillo's tippe-top example with MoreauClassical (as the example does) and save it."""
    root = pathlib.Path(checkout).resolve()
    sys.path.insert(0, str(root))
    import matplotlib

    matplotlib.use("Agg")
    import cardillo.discrete as discrete
    from cardillo.solver import MoreauClassical

    if not hasattr(discrete, "RigidBodyEuler"):  # the example imports it; unused, gone at 1c667a30
        discrete.RigidBodyEuler = type("RigidBodyEuler", (), {})
    spec = importlib.util.spec_from_file_location(
        "cardillo_tippetop", root / "examples" / "tippetop.py"
    )
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    system, top, _, _ = example.make_system(discrete.RigidBody)
    start = time.perf_counter()
    sol = MoreauClassical(system, t_final, dt, atol=1e-12).solve()
    wall = time.perf_counter() - start
    axis = np.array([top.A_IK(t, q)[:, 2] for t, q in zip(sol.t, sol.q)])
    gaps = np.array([system.g_N(t, q) for t, q in zip(sol.t, sol.q)])
    np.savez(out, t=sol.t, q=sol.q, u=sol.u, P_N=sol.P_N, axis=axis, gaps=gaps, wall=wall, dt=dt)


if __name__ == "__main__":
    checkout, dt, t_final, out = sys.argv[1:5]
    cardillo_worker(checkout, float(dt), float(t_final), out)
