"""float32 as a whole-process setting (TIPPEJAX_ENABLE_X64=0), in a subprocess."""

import json
import os
import subprocess
import sys

SCRIPT = r"""
import json, numpy as np, jax
import tippejax as tj
top = tj.default_top()
y0 = tj.initial_state(top, 0.1, 100.0)
sol = tj.simulate(top, y0, 1.0, saveat=np.linspace(0.0, 1.0, 51), throw=False, progress=True)
th = tj.thresholds(top)
print(json.dumps(dict(
    x64=bool(jax.config.jax_enable_x64), dtype=str(sol.theta.dtype),
    ok=bool(sol.result == tj.RESULTS.successful), theta=np.asarray(sol.theta).tolist(),
    n1=float(th.n1), group=tj.classify(top),
    states=tj.steady_states(top, 4e-6).intermediate,
)))
"""


def test_float32_process_runs_and_agrees_with_float64():
    env = dict(os.environ, TIPPEJAX_ENABLE_X64="0")
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True
    ).stdout
    r = json.loads(out.strip().splitlines()[-1])
    assert not r["x64"] and r["dtype"] == "float32" and r["ok"]
    assert r["group"] == "IIb"
    import numpy as np

    import tippejax as tj

    top = tj.default_top()
    ref = tj.simulate(top, tj.initial_state(top, 0.1, 100.0), 1.0, saveat=np.linspace(0.0, 1.0, 51))
    err = np.max(np.abs(np.asarray(r["theta"]) - np.asarray(ref.theta)))
    print(f"float32 process vs float64: max |dtheta| = {err:.2e} rad over 1 s")
    assert err < 1e-3
    assert abs(r["n1"] / float(tj.thresholds(top).n1) - 1) < 1e-6
    ref_states = tj.steady_states(top, 4e-6).intermediate
    assert len(r["states"]) == len(ref_states) == 1
    assert abs(r["states"][0][0] - ref_states[0][0]) < 1e-5
