"""Command line: ``python -m so3jax``."""

import sys


def main(argv=None) -> int:
    import jax.numpy as jnp

    import so3jax as s

    w = jnp.array([0.3, -0.2, 0.9])
    R = s.exp(w)
    print("so3jax demo of the primitives")
    print("w            =", w)
    print("exp(w)       =\n", R)
    print("log(exp(w))  =", s.log(R))
    print("to_quat      =", s.to_quat(R))
    print("ZYX angles   =", [float(a) for a in s.to_euler_zyx(R)])
    print("|R^T R - I|  =", float(s.orthogonality_error(R)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
