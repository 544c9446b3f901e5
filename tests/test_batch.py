"""simulate_batch: a grid of launches in one compiled batch, and sharding over devices."""

import json
import os
import subprocess
import sys

import numpy as np

import tippejax as tj

TS = np.linspace(0.0, 1.0, 21)


def test_batch_equals_single_runs():
    top = tj.default_top()
    thetas, spins = [0.1, 0.4], [30.0, 90.0]
    batch = tj.simulate_batch(top, thetas, spins, 1.0, saveat=TS)
    assert batch.theta.shape == (2, 2, TS.size)
    assert np.all(np.asarray(batch.result == tj.RESULTS.successful))
    for i, th in enumerate(thetas):
        for j, n in enumerate(spins):
            single = tj.simulate(top, tj.initial_state(top, th, n), 1.0, saveat=TS)
            assert np.max(np.abs(np.asarray(batch.theta[i, j]) - np.asarray(single.theta))) < 1e-9
    # A second call with the same shapes reuses the compiled batch (no new trace).
    from tippejax._batch import _batch_run

    before = _batch_run._cached._cache_size() if hasattr(_batch_run, "_cached") else None
    tj.simulate_batch(top, [0.2, 0.3], [40.0, 80.0], 1.0, saveat=TS)
    if before is not None:
        assert _batch_run._cached._cache_size() == before


SCRIPT = r"""
import json, numpy as np, jax
import tippejax as tj
top = tj.default_top()
ts = np.linspace(0.0, 0.5, 11)
sharded = tj.simulate_batch(top, [0.1, 0.2, 0.3], [50.0, 100.0], 0.5, saveat=ts)
plain = tj.simulate_batch(top, [0.1, 0.2, 0.3], [50.0, 100.0], 0.5, saveat=ts, shard=False)
print(json.dumps(dict(devices=jax.device_count(),
    diff=float(np.max(np.abs(np.asarray(sharded.theta) - np.asarray(plain.theta)))),
    shape=list(sharded.theta.shape))))
"""


def test_sharded_batch_on_four_host_devices():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=True
    ).stdout
    r = json.loads(out.strip().splitlines()[-1])
    assert r["devices"] == 4
    assert r["shape"] == [3, 2, 11]  # 6 launches padded to 8 and cut back
    assert r["diff"] < 1e-12


def test_bucketed_batch_equals_unbucketed():
    """buckets > 1 sorts launches by spin into equal-size batches and puts results back."""
    top = tj.default_top()
    thetas, spins = [0.1, 0.4], [90.0, 30.0]  # spins out of order: the sort must be undone
    plain = tj.simulate_batch(top, thetas, spins, 1.0, saveat=TS)
    for buckets in (2, 3):  # 3 buckets of 2: padded from 4 launches to 6
        bucketed = tj.simulate_batch(top, thetas, spins, 1.0, saveat=TS, buckets=buckets)
        assert bucketed.theta.shape == plain.theta.shape == (2, 2, TS.size)
        assert np.all(np.asarray(bucketed.result == tj.RESULTS.successful))
        # equal to about rtol: a member's rounding can depend on the size of its batch
        diff = np.max(np.abs(np.asarray(bucketed.theta) - np.asarray(plain.theta)))
        assert diff < 1e-6, diff
        np.testing.assert_allclose(np.asarray(bucketed.spin[..., 0]),
                                   np.asarray(plain.spin[..., 0]), rtol=1e-12)
