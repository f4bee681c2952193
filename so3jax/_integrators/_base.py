"""Shared pieces of the Lie-group integrators: the solver base and tableaus.

A method is data (a tableau, checked once) plus a small `step`. Tableaus are
frozen dataclasses of tuples, so they are hashable and live in static fields:
XLA sees them as constants and zero coefficients are skipped at trace time.
"""

from __future__ import annotations

import abc
import dataclasses
from fractions import Fraction

import equinox as eqx
import numpy as np

from .._scene import Scene
from .._state import LieState
from .._types import Array


def _tuple(x) -> tuple:
    return tuple(float(Fraction(v)) if isinstance(v, str) else float(v) for v in x)


@dataclasses.dataclass(frozen=True)
class ButcherTableau:
    """An explicit Runge–Kutta tableau (optionally with an embedded pair).

    **Fields:**

    - `a`: strictly lower-triangular rows ``a[i] = (a_i0, ..., a_i,i-1)`` for stages
      ``i = 1 .. s-1`` (stage 0 has no row).
    - `b`: weights, length ``s``.
    - `c`: nodes, length ``s``; checked: ``c_i = sum_j a_ij``.
    - `order`: classical order of ``b``.
    - `b_low`: weights of the embedded lower-order solution (or ``None``).
    - `order_low`: its order.
    """

    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    c: tuple[float, ...]
    order: int
    b_low: tuple[float, ...] | None = None
    order_low: int | None = None
    fsal: bool = False

    def __post_init__(self):
        s = len(self.b)
        if len(self.c) != s or len(self.a) != s - 1:
            raise ValueError("tableau: b, c need s entries and a needs s - 1 rows")
        for i, row in enumerate(self.a, start=1):
            if len(row) != i:
                raise ValueError(f"tableau: row {i} of a must have {i} entries")
            if abs(sum(row) - self.c[i]) > 1e-14:
                raise ValueError(f"tableau: row {i} of a must sum to c[{i}]")
        if self.c[0] != 0:
            raise ValueError("tableau: an explicit method has c[0] = 0")
        if abs(sum(self.b) - 1) > 1e-14:
            raise ValueError("tableau: weights b must sum to 1")
        if self.b_low is not None and abs(sum(self.b_low) - 1) > 1e-14:
            raise ValueError("tableau: embedded weights must sum to 1")

    @classmethod
    def from_fractions(cls, a, b, c, order, b_low=None, order_low=None, fsal=False):
        return cls(
            a=tuple(_tuple(r) for r in a),
            b=_tuple(b),
            c=_tuple(c),
            order=order,
            b_low=None if b_low is None else _tuple(b_low),
            order_low=order_low,
            fsal=fsal,
        )

    @property
    def stages(self) -> int:
        return len(self.b)


@dataclasses.dataclass(frozen=True)
class CFTableau:
    """A commutator-free (Crouch–Grossman type) Lie-group method.

    Each stage rotation is ``R0 exp(h sum_j alpha_1j K_j) exp(h sum_j alpha_2j K_j) ...``
    (factors applied left to right); the vector part uses the plain RK
    coefficients ``a_ij = sum over factors of alpha_j``.

    **Fields:**

    - `stages`: for stages ``i = 1 .. s-1``, a tuple of factors, each a tuple of
      ``i`` coefficients.
    - `final`: the factors of the update, each a tuple of ``s`` coefficients.
    - `c`: nodes; checked against the summed coefficients.
    - `order`: classical order.
    """

    stages: tuple[tuple[tuple[float, ...], ...], ...]
    final: tuple[tuple[float, ...], ...]
    c: tuple[float, ...]
    order: int

    def __post_init__(self):
        s = len(self.c)
        if len(self.stages) != s - 1:
            raise ValueError("CF tableau: need s - 1 stage rows")
        for i, factors in enumerate(self.stages, start=1):
            if any(len(f) != i for f in factors):
                raise ValueError(f"CF tableau: factors of stage {i} need {i} coefficients")
            if abs(sum(map(sum, factors)) - self.c[i]) > 1e-14:
                raise ValueError(f"CF tableau: stage {i} coefficients must sum to c[{i}]")
        if any(len(f) != s for f in self.final):
            raise ValueError("CF tableau: final factors need s coefficients")
        if abs(sum(map(sum, self.final)) - 1) > 1e-14:
            raise ValueError("CF tableau: final coefficients must sum to 1")

    @classmethod
    def from_fractions(cls, stages, final, c, order):
        return cls(
            stages=tuple(tuple(_tuple(f) for f in st) for st in stages),
            final=tuple(_tuple(f) for f in final),
            c=_tuple(c),
            order=order,
        )

    def vector_a(self, i: int) -> tuple[float, ...]:
        """Plain RK coefficients of stage ``i`` (sum over its factors)."""
        factors = self.stages[i - 1]
        # Python floats (weakly typed): NumPy float64 scalars would promote float32 states.
        return tuple(map(float, np.sum(np.array(factors), axis=0))) if factors else (0.0,) * i

    @property
    def vector_b(self) -> tuple[float, ...]:
        return tuple(map(float, np.sum(np.array(self.final), axis=0)))


class AbstractLieSolver(eqx.Module):
    """A one-step method on ``SO(3)^k x R^n``.

    Subclasses provide `order` and ``step(scene, t, y, h) -> (y_next, failed)``,
    where ``failed`` is a bool scalar (an implicit solve did not converge).
    """

    @property
    @abc.abstractmethod
    def order(self) -> int: ...

    @abc.abstractmethod
    def step(self, scene: Scene, t: Array, y: LieState, h: Array) -> tuple[LieState, Array]: ...

    def increment(self, scene: Scene, t: Array, y: LieState, h: Array):
        """One step as ``(dR, x1, failed)`` with ``R1 = R + dR``.

        Used by compensated (Kahan) summation (``simulate(..., compensated=True)``),
        which needs the rotation increment before it is added. Methods override
        it to compute ``dR`` directly; this fallback differences the step, which
        is correct but recovers nothing of the rounding of the sum.
        """
        y1, failed = self.step(scene, t, y, h)
        return y1.R - y.R, y1.x, failed

    @property
    def name(self) -> str:
        return type(self).__name__


def lincomb(coeffs, vectors, h):
    """``h * sum_j coeffs[j] * vectors[j]``, skipping zero coefficients; None if all zero."""
    out = None
    for cj, vj in zip(coeffs, vectors, strict=True):
        if cj == 0.0:
            continue
        term = cj * vj
        out = term if out is None else out + term
    return None if out is None else h * out
