"""The numpy side of a fit: one record (or a batch) and its settings, and the compiled runs.

`Setup` builds the `Data` of each optimisation (which samples, which slow observables, which
tolerance) and runs the compiled functions: the residuals, their Jacobian and the fitted curve
at a point (`evaluate`: the optimisers' steps, `optimise`, and the statistics at the end,
`finish`, both run on it), the losses of many starting points at once (`losses`), and the
statistics from an evaluation (a small program without a solve). Each compiles once per
configuration (`Config`) and shape, whatever the stage.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._bucket import bucket as bucket  # (fit.py and problem.py take it from here)
from .._cache import cacheable, cached_call, compile_ahead, to_device
from .._devices import batch_sharding, shard_over
from .._engine.cpu import own_compiler_options
from .optimise import least_squares, optimise
from .params import assemble, physical
from .problem import (
    NUM_LEVELS,
    U_LIMIT,
    Config,
    Data,
    residuals,
    value_jacobian_solution,
)
from .result import FIT_RESULTS

# Weight of the envelope residuals: an rms error of 0.05 rad in the smoothed tilt weighs as
# much as errors of 0.05 s in all the level times.
ENVELOPE_WEIGHT = NUM_LEVELS / 0.05**2
STAGE_TOL = 1e-4  # optimiser tolerance of the intermediate stages (the last one uses `tol`)
SEARCH_RTOL = 1e-6  # simulation tolerance of the global search (it ranks, it does not fit)
STAGE_RTOL = 1e-7  # simulation tolerance of intermediate stages, unless `rtol` is looser
SEARCH_SLIP_SCALE = 1e-3  # m/s: the least slip scale of a search's law (`data(search=True)`)
CHUNK = 32  # points per batch of simulations in searches and scans (one compilation)


def _committed(tree):
    """`tree` with its arrays committed to their device: the compiled programs are called
    with them many times (each optimiser step), and `cached_call` would otherwise commit
    every input of every call."""
    return jax.tree_util.tree_map(
        lambda x: (
            jax.device_put(x, next(iter(x.devices())))
            if isinstance(x, jax.Array) and not x.committed
            else x
        ),
        tree,
    )


class Setup:
    """One fit's data in numpy (shape `(bsize, N)`) and the template of its `Data`."""

    def __init__(
        self,
        *,
        ts,
        mask,
        weights,
        phi,
        rises,
        template: Data,
        cfg: Config,
        batched: bool,
        tol: float,
        rtol: float,
    ):
        self.ts = ts
        self.n = ts.size
        self.mask = mask  # (bsize, N) bool: a usable sample
        self.w = weights  # (bsize, N)
        self.phi = phi  # (bsize, N) or None
        self.rises = rises  # (bsize,) bool
        self.bsize = mask.shape[0]
        self.cfg = cfg
        self.batched = batched
        self.tol = tol
        self.rtol = rtol
        # a batch's records split over the devices (`jax.sharding`), one core each
        self.sharding = batch_sharding(self.bsize) if batched else None
        # ... each device running its records' solves alone (`shard_over`)
        self.mesh = None if self.sharding is None else self.sharding.mesh
        self.template = self.place(template)
        self.fitted = np.ones_like(mask)  # the samples a fit may use (trim shortens it)
        self.padded = template.ts.shape[-1]  # the data arrays' length (a bucket, >= n)
        self._data = {}  # the last few Data by the arguments of `data` (equal arguments: one object)
        self._evaluations = {}  # the last few evaluations by (Data, u)

    def subset(self, idx) -> "Setup":
        """The records `idx` of a batch (indices into it) as a setup of their own: one record
        as an unbatched setup (the programs of single fits), several as a smaller batch. A
        batch's records that a stage need not run again are left out of it: vmapped, every
        record pays for the slowest one's search."""
        idx = np.asarray(idx, int)
        one = idx.size == 1

        def pick(x):  # the records' rows, shape (len(idx), ...)
            return np.asarray(x)[idx]

        template = jax.tree_util.tree_map(
            lambda x: to_device(pick(x)[0] if one else pick(x), x.dtype), self.template
        )
        sub = Setup(
            ts=self.ts,
            mask=pick(self.mask),
            weights=pick(self.w),
            phi=None if self.phi is None else pick(self.phi),
            rises=pick(self.rises),
            template=template,
            cfg=self.cfg,
            batched=not one,
            tol=self.tol,
            rtol=self.rtol,
        )
        sub.fitted = pick(self.fitted)
        return sub

    def with_free(self, free: tuple[str, ...]) -> "Setup":
        """The same records and guess with other free parameters (`free`): the setup of a
        question about the fit, such as whether freeing the launch time would help
        (`launch.py`)."""
        cfg = eqx.tree_at(lambda c: c.free, self.cfg, tuple(free))
        other = Setup(
            ts=self.ts,
            mask=self.mask,
            weights=self.w,
            phi=self.phi,
            rises=self.rises,
            template=self.template,
            cfg=cfg,
            batched=self.batched,
            tol=self.tol,
            rtol=self.rtol,
        )
        other.fitted = self.fitted
        return other

    def place(self, tree):
        """`tree`'s arrays committed to a device, or in a sharded batch split over the devices
        along their first (the record) axis."""
        if self.sharding is None:
            return _committed(tree)
        return jax.tree_util.tree_map(
            lambda x: jax.device_put(x, self.sharding) if isinstance(x, jax.Array) else x, tree
        )

    def pad(self, x: np.ndarray) -> np.ndarray:
        """`x` of shape (bsize, n) padded with zeros to the bucket length."""
        return np.concatenate([x, np.zeros(x.shape[:-1] + (self.padded - self.n,), x.dtype)], -1)

    def data(
        self,
        *,
        window_end=None,
        theta=True,
        slow=0.0,
        tol=STAGE_TOL,
        rtol=None,
        final=False,
        pin=(),
        steps=None,
        search=False,
    ) -> Data:
        """`Data` for one optimisation: tilt samples up to `window_end` (all if None; none if
        `theta` is False; a scalar or one per record) and the slow observables with weight
        `slow` (per record or scalar). Without slow observables the simulation stops at the
        window's end. It runs at `rtol` if given, else at the fit's own `rtol` when `final`,
        else at `STAGE_RTOL` (or the fit's, if looser). The free parameters named in `pin`
        are held where they are. `steps` caps the optimiser's steps (default: the fit's
        `max_steps`). A `search` (the stages that rank and scan trial points, not those that
        fit) simulates a law whose motion converges as its slip scale goes to 0 with a slip
        scale of at least `SEARCH_SLIP_SCALE` (see `AbstractFriction._with_slip_floor`)."""
        key = tuple(
            None if a is None else (np.asarray(a).dtype.str, np.shape(a), np.asarray(a).tobytes())
            for a in (
                window_end,
                theta,
                slow,
                tol,
                rtol,
                final,
                tuple(pin),
                steps,
                search,
                self.fitted,
            )
        )
        if key not in self._data:
            if len(self._data) >= 8:  # (a Data holds the whole batch's arrays: keep a few)
                del self._data[next(iter(self._data))]
            self._data[key] = self._make_data(
                window_end=window_end,
                theta=theta,
                slow=slow,
                tol=tol,
                rtol=rtol,
                final=final,
                pin=pin,
                steps=steps,
                search=search,
            )
        return self._data[key]

    def _make_data(self, *, window_end, theta, slow, tol, rtol, final, pin, steps, search) -> Data:
        ts, bsize = self.ts, self.bsize
        use = self.mask & self.fitted
        t_end = np.full(bsize, ts[-1])
        if window_end is not None:
            window_end = np.broadcast_to(np.asarray(window_end, float), (bsize,))
            use = use & (ts[None, :] <= window_end[:, None] + 1e-12)
            if not np.any(np.asarray(slow) > 0):  # only tilt samples: simulate the window only
                t_end = np.minimum(t_end, window_end)
        theta_mask = np.broadcast_to(np.asarray(theta, bool).reshape(-1, 1), use.shape)
        w = np.where(use & theta_mask, self.w, 0.0)
        dtype = self.template.theta_obs.dtype
        pw = self.template.phi_weights
        if self.phi is not None:
            pw = np.where(np.isfinite(self.phi) & use & theta_mask, self.w, 0.0)
        slow = np.broadcast_to(np.asarray(slow, float), (bsize,))
        if rtol is None:
            rtol = self.rtol if final else max(self.rtol, STAGE_RTOL)
        fields = dict(
            weights=self.pad(w),
            phi_weights=self.pad(pw) if self.phi is not None else pw,
            level_weight=slow * self.rises,
            envelope_weight=slow * ENVELOPE_WEIGHT,
            tol=np.full(bsize, max(tol, self.tol)),
            rtol=np.full(bsize, rtol),
            slip_floor=np.full(bsize, SEARCH_SLIP_SCALE if search else 0.0),
            t_end=t_end,
            pinned=np.broadcast_to(
                np.array([n in pin for n in self.cfg.free], float), (bsize, len(self.cfg.free))
            ),
            steps=np.full(
                bsize,
                float(self.cfg.max_steps if steps is None else min(steps, self.cfg.max_steps)),
            ),
        )
        # (indexed in numpy: a jax index is a small program to compile in each new process)
        fields = {k: np.asarray(v) if self.batched else np.asarray(v)[0] for k, v in fields.items()}
        fields = self.place({k: to_device(v, dtype) for k, v in fields.items()})
        names = tuple(fields)
        return eqx.tree_at(
            lambda d: tuple(getattr(d, k) for k in names),
            self.template,
            tuple(fields[k] for k in names),
        )

    def evaluate(self, u, data: Data):
        """The residuals, their Jacobian (in `u`) and the simulated curves at `u`: one
        forward-mode solve per recording, in the one compiled program that every
        optimisation step and `finish` run."""
        u = np.asarray(u, self.template.ts.dtype)
        key = (id(data), u.shape, u.tobytes())
        if key in self._evaluations:  # (the optimiser's last accepted point, then `finish`)
            return self._evaluations[key][1]
        # (the fit's programs go to the persistent cache too, `_cache/`)
        out = _own_call(
            _run_evaluate, to_device(u), data, cfg=self.cfg, batched=self.batched, mesh=self.mesh
        )
        if len(self._evaluations) >= 8:
            del self._evaluations[next(iter(self._evaluations))]
        self._evaluations[key] = (data, out)  # (holding `data` keeps its id unique)
        return out

    def optimise(self, u, data: Data):
        """One optimisation from `u` on the loss `data` describes: `(u, history, steps, code)`
        (see `optimise.py`)."""
        cfg = self.cfg
        if cfg.method == "adam":
            return _own_call(_run_optimise, u, data, cfg=cfg, batched=self.batched, mesh=self.mesh)
        dtype = self.template.ts.dtype

        def evaluate(v):
            value, jac, _ = self.evaluate(v if self.batched else v[0], data)
            value, jac = np.asarray(value), np.asarray(jac)
            return (value, jac) if self.batched else (value[None], jac[None])

        u0 = np.asarray(u, dtype).reshape(-1, len(cfg.free))
        tol = np.asarray(data.tol).reshape(-1)
        steps = np.asarray(data.steps).reshape(-1)
        end, history, count, codes = least_squares(
            evaluate,
            u0,
            tol=tol,
            steps=steps,
            max_steps=cfg.max_steps,
            damped=cfg.method == "levenberg_marquardt",
        )
        if not self.batched:
            end, history, count, codes = end[0], history[0], count[0], codes[0]
        # (the codes as an item of FIT_RESULTS: one made and its value replaced)
        code = eqx.tree_at(lambda c: c._value, FIT_RESULTS.successful, to_device(codes))
        return to_device(end, dtype), to_device(history, dtype), to_device(count), code

    def optimise_many(self, u, data: Data):
        """`optimise` from each of the starting points `u` (shape `(K, *batch, p)`) in turn.
        Returns the end points, shape `(K, *batch, p)`, and their step counts.

        One after the other, through the program the stages already compiled: a vmapped batch
        of K optimisations is a program of its own, and compiling it (forward-mode Jacobians
        through the solver, K wide) cost minutes on 2 cores, more than the K optimisations; in
        lock-step the batch would also run until its slowest member stops."""
        ends, steps = [], []
        for k in range(u.shape[0]):
            end, _, count, _ = self.optimise(jnp.asarray(u[k]), data)
            ends.append(end)
            steps.append(count)
        return jnp.stack(ends), jnp.stack([jnp.asarray(c) for c in steps])

    def losses(self, u, data: Data) -> np.ndarray:
        """Loss of each of the points `u` (shape `(K, *batch, p)`), in batches of `CHUNK`
        (the last one padded), so that every search and scan shares one compilation. Not
        finite (a failed simulation): inf."""
        u = np.asarray(u)
        k = u.shape[0]
        out = []
        for lo in range(0, k, CHUNK):
            part = u[lo : lo + CHUNK]
            part = np.concatenate([part, np.repeat(part[-1:], CHUNK - part.shape[0], 0)])
            out.append(
                np.asarray(
                    _own_call(
                        _run_losses,
                        to_device(part, self.template.ts.dtype),
                        data,
                        cfg=self.cfg,
                        batched=self.batched,
                        mesh=self.mesh,
                    )
                )
            )
        losses = np.concatenate(out)[:k]
        return np.where(np.isfinite(losses), losses, np.inf)

    def compile_losses_ahead(self) -> None:
        """Start compiling the program of `losses` on the side (`_cache.compile_ahead`): on
        two cores it compiles while the first evaluation is traced, instead of after it (a cold
        first fit about 1.2 s shorter in interleaved runs: XLA's compiler already uses most of
        both cores, so only the tracing overlaps)."""
        shape = (CHUNK,) + ((self.bsize,) if self.batched else ()) + (len(self.cfg.free),)
        _own_call(
            _run_losses,
            to_device(np.zeros(shape), self.template.ts.dtype),
            self.data(),
            cfg=self.cfg,
            batched=self.batched,
            mesh=self.mesh,
            ahead=True,
        )

    def nutation_cycles(self, spin_u):
        """Number of fast-nutation cycles, C|n|/(2 pi A) x the record, at spin coordinates
        `spin_u` (one per record)."""
        base = self.template.base
        spin = np.abs(np.asarray(base.launch["spin"])) * np.exp(np.asarray(spin_u))
        period = 2 * np.pi * np.asarray(base.top["A"]) / (np.asarray(base.top["C"]) * spin)
        return (self.ts[-1] - self.ts[0]) / period

    def finish(self, u, code, data: Data):
        """The fit's statistics at `u` (`finish`), from `evaluate` at `u` clipped to the trust
        region."""
        inside = np.clip(np.asarray(u), -U_LIMIT, U_LIMIT)
        value, jac, run = self.evaluate(inside, data)
        if self.batched and np.ndim(code._value) == 0:  # one code for every record
            code = eqx.tree_at(
                lambda c: c._value, code, to_device(np.full(self.bsize, np.asarray(code._value)))
            )
        return _own_call(
            _run_finish,
            u,
            code,
            data,
            value,
            jac,
            run,
            cfg=self.cfg,
            batched=self.batched,
            mesh=self.mesh,
        )


def _own_call(fn, *args, ahead=False, **static):
    """`cached_call` (or with `ahead`, `compile_ahead`) of one of the fit's programs, traced
    for the persistent cache (`cacheable`) and compiled with tippejax's CPU options on a CPU
    (`tippejax._engine.cpu`), which compile and run the fit's programs sooner."""
    options = own_compiler_options()
    with cacheable():
        if ahead:
            return compile_ahead(fn, *args, compiler_options=options, **static)
        return cached_call(fn, *args, compiler_options=options, **static)


def _over_records(fn, mesh, *args):
    """`jax.vmap(fn)(*args)` over a batch's records (the first axis of every array), each
    device running its own records alone where the records are split over devices (`mesh`)."""
    if mesh is None:
        return jax.vmap(fn)(*args)
    return shard_over(jax.vmap(fn), mesh, "batch", args, (True,) * len(args))


@eqx.filter_jit
def _run_optimise(u0, data, cfg, batched, mesh=None):
    if batched:
        return _over_records(lambda u, d: optimise(u, d, cfg), mesh, u0, data)
    return optimise(u0, data, cfg)


@eqx.filter_jit
def _run_evaluate(u, data, cfg, batched, mesh=None):
    if batched:
        return _over_records(lambda v, d: value_jacobian_solution(v, d, cfg), mesh, u, data)
    return value_jacobian_solution(u, data, cfg)


@eqx.filter_jit
def _run_losses(u, data, cfg, batched, mesh=None):
    def loss(v, d):
        r = residuals(v, d, cfg)
        return 0.5 * jnp.sum(r**2)

    if not batched:
        return jax.vmap(lambda v: loss(v, data))(u)
    # u: (starts, records, p); over the records on the outside, the starts inside
    by_record = _over_records(
        lambda v, d: jax.vmap(lambda w: loss(w, d))(v), mesh, jnp.swapaxes(u, 0, 1), data
    )
    return jnp.swapaxes(by_record, 0, 1)


def finish(u, code, data: Data, value, jac_u, sol, cfg: Config):
    """Covariance and the fitted curve at the final coordinates (one record), from the
    residuals `value`, their Jacobian `jac_u` and the simulation `sol` at `u` clipped to the
    trust region (`Setup.evaluate`)."""
    at_edge = jnp.any(jnp.abs(u) >= U_LIMIT * (1 - 1e-6))
    u = jnp.clip(u, -U_LIMIT, U_LIMIT)
    values = physical(u, data.base, cfg.free)
    dp_du = jax.jacfwd(
        lambda v: jnp.stack([physical(v, data.base, cfg.free)[n] for n in cfg.free])
    )(u)
    n_used = jnp.sum(data.weights > 0) + (jnp.sum(data.phi_weights > 0) if cfg.has_phi else 0)
    p = len(cfg.free)
    rss = jnp.sum(value**2)
    s2 = rss / jnp.maximum(n_used - p, 1).astype(rss.dtype)
    # J_p = J_u (du/dp); Sigma = s2 (J_p^T J_p)^{-1} = s2 G (J_u^T J_u)^{-1} G^T with G = dp/du.
    jtj = jac_u.T @ jac_u
    scale = 1.0 / jnp.sqrt(jnp.maximum(jnp.diag(jtj), 1e-300))
    inv_scaled = jnp.linalg.inv(scale[:, None] * jtj * scale[None, :])
    cov_u = s2 * scale[:, None] * inv_scaled * scale[None, :]
    cov = dp_du @ cov_u @ dp_du.T
    std = jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0))
    std = jnp.where(jnp.isfinite(std), std, jnp.inf)
    corr = cov / (std[:, None] * std[None, :])
    theta_fit = jnp.where(sol.ts > sol.t_contact_loss, jnp.nan, sol.theta)
    phi_fit = jnp.where(jnp.isfinite(theta_fit), sol.phi, jnp.nan)
    if not cfg.has_phi:
        phi_fit = jnp.full_like(phi_fit, jnp.nan)
    used = data.weights > 0
    failed = jnp.any(used & ~jnp.isfinite(theta_fit))
    top, y0 = assemble(values, data.base)
    vector = jnp.stack([values[n] for n in cfg.free])
    t0 = values["t0"] if "t0" in values else data.t0
    return dict(
        top=top,
        y0=y0,
        t0=t0,
        values=vector,
        std_errors=std,
        covariance=cov,
        correlation=corr,
        theta_fit=theta_fit,
        phi_fit=phi_fit,
        loss=0.5 * rss,
        result=FIT_RESULTS.where(
            jnp.all(jnp.isfinite(u)),
            FIT_RESULTS.where(
                failed,
                FIT_RESULTS.simulation_failed,
                FIT_RESULTS.where(at_edge, FIT_RESULTS.outside_trust_region, code),
            ),
            FIT_RESULTS.optimiser_failed,  # (Gauss-Newton can accept a step to nan)
        ),
    )


@eqx.filter_jit
def _run_finish(u, code, data, value, jac, sol, cfg, batched, mesh=None):
    if batched:
        return _over_records(lambda *a: finish(*a, cfg), mesh, u, code, data, value, jac, sol)
    return finish(u, code, data, value, jac, sol, cfg)
