"""Type aliases shared across tippejax (in the style of diffrax's `_custom_types.py`)."""

from typing import Union

import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

RealScalarLike = Union[float, int, np.floating, np.integer, Float[ArrayLike, ""]]
Scalar = Float[Array, ""]
Vector3 = Float[Array, "3"]
Vector2 = Float[Array, "2"]

__all__ = [
    "Array",
    "ArrayLike",
    "Bool",
    "Float",
    "Int",
    "RealScalarLike",
    "Scalar",
    "Vector2",
    "Vector3",
]
