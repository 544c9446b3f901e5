"""The table of dynamic levels of model, one file each, behind `base.AbstractLevel`.

`LEVELS` is the table of levels the engine knows, cheapest last; a new level is a new file and
one line here.
"""

from .base import AbstractLevel as AbstractLevel, Conditions as Conditions
from .full import FullLevel
from .gyroscopic import GyroscopicLevel
from .routhian import RouthianLevel
from .so3 import SO3Level

LEVELS: dict[str, AbstractLevel] = {
    "full": FullLevel(),
    "so3": SO3Level(),
    "routhian": RouthianLevel(),
    "gyroscopic": GyroscopicLevel(),
}
