"""The command line's ``--inertia``: read it, check it, rebuild a scene with it.

Shared by ``python -m so3jax`` (`so3jax.__main__`), ``sweep`` and ``tune``
(`so3jax._cli_sweep`). The checks are those of `RigidBody` (symmetric within
``1e-6`` of the largest entry, positive definite), done in NumPy while the
options are parsed, before any scene is built; principal moments that violate
the triangle inequality, which `RigidBody` accepts with a warning, are an error
here: no rigid body has them.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import warnings

import numpy as np

#: Help text of ``--inertia`` (the scene-specific part is added by each command).
INERTIA_HELP = (
    "the body's inertia in kg m^2: 3 principal moments J1 J2 J3 (diag) or the 9 entries of "
    "the matrix, row by row (products of inertia allowed); symmetric, positive definite, "
    "principal moments meeting the triangle inequality J1 + J2 >= J3"
)

#: `RigidBody`'s tolerances: asymmetry relative to the largest entry, triangle slack.
_SYMMETRY_RTOL = 1e-6
_TRIANGLE_RTOL = 1e-12


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in kg m^2, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number in kg m^2, got {text!r}")
    return value


def check_inertia(values) -> np.ndarray:
    """An inertia from the command line, checked as `RigidBody` checks it, and stricter.

    **Arguments:**

    - `values`: 3 principal moments or the 9 entries of the matrix, row by row.

    **Returns:** the moments, shape `(3,)`, or the matrix, shape `(3, 3)` (float64),
    as given.

    **Raises:** ``ValueError`` (a one-line message) for another count, a non-finite
    entry, an asymmetric matrix, a matrix that is not positive definite, or
    principal moments that violate the triangle inequality ``J1 + J2 >= J3``.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.shape not in ((3,), (9,)):
        raise ValueError(
            "expected 3 principal moments J1 J2 J3 or the 9 entries of the inertia matrix "
            f"(row by row), in kg m^2; got {v.size} number{'s' if v.size != 1 else ''}"
        )
    if not np.all(np.isfinite(v)):
        raise ValueError(f"expected finite numbers, got {_row(v)}")
    if v.shape == (3,):
        if v.min() <= 0:
            raise ValueError(
                f"principal moments must be positive (a positive-definite inertia), got {_row(v)}"
            )
        moments = np.sort(v)
    else:
        J = v.reshape(3, 3)
        scale = max(np.abs(J).max(), np.finfo(np.float64).tiny)
        i, j = np.unravel_index(np.argmax(np.abs(J - J.T)), (3, 3))
        if abs(J[i, j] - J[j, i]) > _SYMMETRY_RTOL * scale:
            raise ValueError(
                f"the inertia matrix must be symmetric: entry ({i + 1}, {j + 1}) is "
                f"{J[i, j]:g} but ({j + 1}, {i + 1}) is {J[j, i]:g}"
            )
        moments = np.linalg.eigvalsh(0.5 * (J + J.T))
        if moments.min() <= 0:
            raise ValueError(
                "the inertia matrix must be positive definite; its principal moments "
                f"(eigenvalues) are {_row(moments)}"
            )
        v = J
    a, b, c = moments
    if a + b < c * (1 - _TRIANGLE_RTOL):
        raise ValueError(
            f"principal moments {_row(moments)} violate the triangle inequality J1 + J2 >= J3 "
            f"({a:g} + {b:g} < {c:g}): no rigid body has them (so3jax.RigidBody accepts "
            "them with a warning, from Python)"
        )
    return v


def _row(v) -> str:
    return "(" + ", ".join(f"{x:g}" for x in np.ravel(v)) + ")"


class _InertiaAction(argparse.Action):
    def __call__(self, parser, namespace, values, option_string=None):
        try:
            setattr(namespace, self.dest, check_inertia(values))
        except ValueError as e:
            raise argparse.ArgumentError(self, str(e)) from None


def add_inertia_option(parser: argparse.ArgumentParser, applies: str) -> None:
    """Add ``--inertia J ...`` (3 or 9 numbers, checked on parsing) to ``parser``.

    **Arguments:**

    - `parser`: the command's parser.
    - `applies`: what the inertia replaces in this command's scenes (a clause for
      the help text).
    """
    parser.add_argument(
        "--inertia",
        nargs="+",
        type=_number,
        action=_InertiaAction,
        default=None,
        metavar="J",
        help=f"{INERTIA_HELP}; {applies} (default: the scene's)",
    )


def inertia_matrix(inertia) -> np.ndarray:
    """The `(3, 3)` float64 matrix of principal moments `(3,)` or a matrix `(3, 3)`."""
    J = np.asarray(inertia, dtype=np.float64)
    return np.diag(J) if J.shape == (3,) else J


def describe_inertia(J) -> str:
    """``diag(J1, J2, J3) kg m^2`` or the matrix row by row, shortest digits of its dtype."""
    J = np.asarray(J)

    def num(x):
        text = str(J.dtype.type(x))  # the shortest digits that round-trip in its dtype
        return text[:-2] if text.endswith(".0") else text

    if J.shape == (3,) or np.count_nonzero(J - np.diag(np.diag(J))) == 0:
        d = J if J.shape == (3,) else np.diag(J)
        return f"diag({', '.join(num(x) for x in d)}) kg m^2"
    rows = ("[" + ", ".join(num(x) for x in row) + "]" for row in J)
    return f"[{', '.join(rows)}] kg m^2"


@contextlib.contextmanager
def checked_inertia():
    """Silence `RigidBody`'s triangle-inequality warning for an inertia checked in float64.

    A float32 cast can move moments that meet the inequality with equality (a flat
    plate, ``J1 + J2 = J3``) by an ulp to the other side.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*violate the triangle inequality")
        yield


def with_inertia(scene, inertia):
    """``scene`` rebuilt by its constructor with the body inertia ``inertia``
    (`Scene.with_inertia`: `RigidBody` recomputes ``J^-1``, a quadrotor samples its
    held control at ``t = 0`` anew).

    **Arguments:**

    - `scene`: a scene with a body inertia (`Scene.with_inertia`).
    - `inertia`: 3 principal moments or a `(3, 3)` matrix, checked by `check_inertia`.

    **Returns:** a scene of the same type, in the dtype of ``scene``.
    """
    from ._dynamics import RigidBody

    with checked_inertia():
        body = RigidBody(np.asarray(inertia, scene.y0.R.dtype))
    try:
        return scene.with_inertia(body)
    except ValueError as err:
        raise ValueError(f"--inertia: {err}") from None


def scene_inertia(scene) -> np.ndarray:
    """The `(3, 3)` inertia a scene simulates (its body's, or its vehicle's)."""
    body = scene.vehicle.body if hasattr(scene, "vehicle") else scene.body
    return np.asarray(body.inertia)
