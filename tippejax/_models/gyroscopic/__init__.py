"""The gyroscopic level: its slow manifold, its chart, the level and its launch projections."""

from .averaged import (
    AVERAGING_NODES as AVERAGING_NODES,
    AveragedProjection as AveragedProjection,
    LaunchTransient as LaunchTransient,
    average_launch as average_launch,
    launch_transient as launch_transient,
)
from .base import (
    PROJECTIONS as PROJECTIONS,
    AbstractProjection as AbstractProjection,
    projection_of as projection_of,
)
from .chart import (
    BALANCE_MARGIN as BALANCE_MARGIN,
    HAND_OVER_MARGIN as HAND_OVER_MARGIN,
    NUTATION_LAUNCH_MAX as NUTATION_LAUNCH_MAX,
    NUTATION_MAX as NUTATION_MAX,
    entry_margin as entry_margin,
    validity as validity,
)
from .coordinate import (
    POLE as POLE,
    cos_sin as cos_sin,
    log_tan_half as log_tan_half,
    theta_of as theta_of,
)
from .level import GyroscopicLevel as GyroscopicLevel
from .linear import (
    LinearProjection as LinearProjection,
    linear_projection as linear_projection,
    linear_state as linear_state,
    project_launch as project_launch,
)
from .manifold import (
    SlowManifold as SlowManifold,
    balance_discriminant as balance_discriminant,
    gyroscopic_theta_dot as gyroscopic_theta_dot,
    limit_theta_dot as limit_theta_dot,
    precession_rate as precession_rate,
    slow_manifold as slow_manifold,
)
from .modes import NUTATION_FLOOR as NUTATION_FLOOR
from .nutation import (
    Nutation as Nutation,
    nutation_damping as nutation_damping,
    nutation_frequency as nutation_frequency,
)
from .settle import (
    SETTLE_AMPLITUDE as SETTLE_AMPLITUDE,
    SETTLE_TIME_MAX as SETTLE_TIME_MAX,
    settle_time as settle_time,
)
from .state import GyroscopicLevelState as GyroscopicLevelState

# the names `_maps/slow_entry.py`, tests and benchmarks import
_projection = linear_projection
_linear_state = linear_state
