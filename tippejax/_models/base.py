r"""The interface every dynamic level of model implements, and its event conditions.

A level is a final `eqx.Module` with no fields of its own beyond static configuration. The
engine (`tippejax._engine`) calls only the methods below and never branches on a level's
name: adding a level is a new file in `tippejax/_models/` and one line in `LEVELS`
(`tippejax/_models/levels.py`).

Event conditions (`Conditions`) are scalars that are positive while the level describes the
motion and fall through zero at the event:

- `contact`: the numerator of $R_n$ times its denominator, $R_n D$ (`docs/notes.md`, Contact loss): zero when
  the top leaves the table;
- `singular`: the denominator $D$ of $R_n$ (eq. reactie), zero at the Painleve-type singularity
  of friction proportional to $R_n$ (`docs/notes.md`, The R_n singularity);
- `upright`: the vertical component of the symmetry axis, $a_Z = \cos\theta$; it falls through
  zero when $\theta$ crosses $\pi/2$ upwards (the inversion);
- `chart`: positive inside the level's chart (the Routhian chart ends near the poles; the
  gyroscopic level's domain ends where gyroscopic balance is lost; the full level of a top with
  a stem ends just before the stem touches the table, and hands over to the stem level); a
  level without a chart edge returns 1;
- `events`: a level's own observed events (`AbstractLevel.observed_events`), by name: the stem
  level's stem touch and the ball's return to the table.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from .._friction.base import AbstractFriction
from .._friction.viscous import Viscous
from .._state import State
from .._top import TippeTop


class Conditions(eqx.Module):
    """Event conditions of one state (see the module docstring). Each is a scalar."""

    contact: Float[Array, ""]
    singular: Float[Array, ""]
    upright: Float[Array, ""]
    chart: Float[Array, ""]
    events: dict[str, Float[Array, ""]] = eqx.field(default_factory=dict)

    def get(self, name: str) -> Float[Array, ""]:
        return self.events[name] if name in self.events else getattr(self, name)


CONDITION_NAMES = ("contact", "singular", "upright", "chart")


class AbstractLevel(eqx.Module):
    """One level of model: its state, vector field, conversions and event conditions.

    **Class attributes:**

    - `name`: the level's name in `simulate(model=...)`.
    - `friction_model`: `"full"` if the friction law sees the horizontal velocity of the centre
      of mass, `"so3"` if it is dropped; used for the observed energy and normal force.
    - `has_chart`: whether the level's coordinates end somewhere (then `conditions().chart`
      falls through zero there and the run continues in `fallback`, or stops, see below).
    - `chart_end_result`: for a level with a chart and no fallback, the name of the `RESULTS`
      member the run reports when the chart ends (the run stops there; a state outside the
      chart at `t0` is not integrated).
    - `friction_laws`: the friction laws (`AbstractFriction` subclasses) the level is derived
      for; `takes_friction` asks it. Default: the viscous law alone (the Routhian and
      gyroscopic reductions use its form); the full and SO(3) levels take every law.
    - `observed_events`: the names of the level's own observed events (keys of
      `Conditions.events`); the chain reports the first downward crossing of each
      (`ChainOutput.level_events`). Default: none.

    **Static option:** `body` (default True), see below.
    """

    name: ClassVar[str]
    friction_model: ClassVar[str]
    has_chart: ClassVar[bool] = False
    chart_end_result: ClassVar[str | None] = None
    slow_flow: ClassVar[bool] = False
    unmodelled: ClassVar[tuple[str, ...]] = ()
    """The observed `Solution` fields the level does not model: `simulate` returns them as nan
    at the save times the level produced (the SO(3) and Routhian levels drop the translation;
    the gyroscopic level also the nutation's body angle, normal force and slip)."""
    friction_laws: ClassVar[tuple[type[AbstractFriction], ...]] = (Viscous,)
    observed_events: ClassVar[tuple[str, ...]] = ()
    body: bool = eqx.field(static=True, default=True, kw_only=True)
    r"""Whether the level carries the body vector (`State.body`, and with it $\psi$). The full
    and SO(3) levels carry it as 4 more state components (`full.spin_frame_rates`); without it
    their state is the axis and angular velocity alone (and the translation), and `to_state`
    gives a body vector of nans. The Routhian and gyroscopic levels report $\psi$ from angles
    they carry anyway, and pass the option on to their fallback."""
    by_components: bool = eqx.field(static=True, default=False, kw_only=True)
    """Whether the full and SO(3) levels evaluate their field and conditions with the algebra
    written out by components (`_rigid_body.rigid_body_dynamics_by_components`, the same
    numbers): the form for a batch whose members are one state's fast axis (shared steps);
    everywhere else the vector form is the cheaper. Other levels ignore it."""

    @abc.abstractmethod
    def from_state(self, top: TippeTop, state: State) -> PyTree:
        """The level's state for a (single) common `State`."""

    @abc.abstractmethod
    def to_state(self, top: TippeTop, y: PyTree) -> State:
        """The common `State` of a (single) level state."""

    @abc.abstractmethod
    def vector_field(self, t, y: PyTree, top: TippeTop) -> PyTree:
        """Time derivative of a single (unbatched) level state; diffrax's `f(t, y, args)`."""

    @abc.abstractmethod
    def conditions(self, top: TippeTop, y: PyTree) -> Conditions:
        """Event conditions of a single level state."""

    def condition_floors(self, top: TippeTop) -> dict[str, Array] | None:
        """The rounding level of each watched condition that can sit at zero (by name), below
        which the watch does not count its sign changes; None (default): every sign counts.
        A condition that stays within its rounding of zero (the ball's gap at a hand-over
        where the normal force vanishes) would otherwise show a hidden crossing in every step,
        however short, and stall the solve."""
        del top
        return None

    def takes_friction(self, friction: AbstractFriction) -> bool:
        """Whether the level's equations hold for this friction law (`friction_laws`)."""
        return isinstance(friction, self.friction_laws)

    def in_chart(self, top: TippeTop, state: State) -> Array:
        """Whether `state` can be represented in this level's coordinates."""
        del top, state
        return jnp.array(True)

    def fallback(self) -> AbstractLevel | None:
        """The level a run continues in when this one's chart ends (None: no chart)."""
        return None

    def for_top(self, top: TippeTop) -> AbstractLevel:
        """The level as it runs `top` (the chain asks it first): itself, unless the top's
        structure changes it (the full level of a top with a stem: `FullLevel.stem`)."""
        del top
        return self

    def common_state(self, top: TippeTop, state: State) -> State:
        """A launch's common `State` in the form this level's chain carries from segment to
        segment (the chain asks it after `for_top`; leading axes allowed): `state` itself,
        unless the chain's states carry more (a chain through the stem level: the height)."""
        del top
        return state

    def error_norm(self, scaled_error: PyTree) -> Array:
        """Norm of the scaled local error used by the step-size controller (RMS by default)."""
        leaves = [jnp.ravel(x) for x in jax.tree_util.tree_leaves(scaled_error)]
        flat = jnp.concatenate(leaves)
        return jnp.sqrt(jnp.mean(flat**2))
