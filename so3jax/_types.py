"""Array aliases that say shapes (jaxtyping). Checked at run time in tests only."""

from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

Scalar = Float[Array, "*batch"]
Vec3 = Float[Array, "*batch 3"]
Quat = Float[Array, "*batch 4"]
Mat3 = Float[Array, "*batch 3 3"]
Rot = Float[Array, "*batch 3 3"]

__all__ = [
    "Array",
    "ArrayLike",
    "Bool",
    "Float",
    "Int",
    "PRNGKeyArray",
    "Scalar",
    "Vec3",
    "Quat",
    "Mat3",
    "Rot",
]
