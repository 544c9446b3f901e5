"""The table of dynamic levels of model, one file each, behind `base.AbstractLevel`.

`LEVELS` is the table of levels the engine knows, cheapest last; a new level is a new file and
one line here.
"""

from .._top import TippeTop
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


def levels_taking(friction) -> tuple[str, ...]:
    """The names of the levels whose equations hold for the friction law `friction`."""
    return tuple(name for name, level in LEVELS.items() if level.takes_friction(friction))


def check_friction(model: str, top: TippeTop) -> None:
    """Raise `ValueError` if the level `model` is not derived for the top's friction law,
    naming the levels that take it."""
    level = LEVELS[model]
    if level.takes_friction(top.friction):
        return
    law = type(top.friction).__name__
    raise ValueError(
        f"model={model!r} is derived for the friction law(s) "
        f"{', '.join(c.__name__ for c in level.friction_laws)} only, and this top has a "
        f"{law} law. Use one of the levels that take it: "
        f"{', '.join(repr(m) for m in levels_taking(top.friction))}."
    )
