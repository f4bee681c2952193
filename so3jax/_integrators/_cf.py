"""Commutator-free Lie-group methods: Lie–Euler, Crouch–Grossman, CF4.

Each stage moves along a product of exponentials of combinations of the
frozen stage velocities; no ``dexp^-1`` and no commutators are needed.

References: P. E. Crouch, R. Grossman, "Numerical integration of ordinary
differential equations on manifolds", J. Nonlinear Sci. 3 (1993) 1–33;
B. Owren, A. Marthinsen, "Runge–Kutta methods adapted to manifolds and based
on rigid frames", BIT 39 (1999) 116–142; E. Celledoni, A. Marthinsen,
B. Owren, "Commutator-free Lie group methods", Future Gener. Comput. Syst. 19
(2003) 341–352.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .._so3 import _mm
from .._state import LieState
from .._updates import _expm1, _rmul_exp
from ._base import AbstractLieSolver, CFTableau, lincomb


def _move(R, factors, xis, h):
    for alpha in factors:
        u = lincomb(alpha, xis, h)
        if u is not None:
            R = _rmul_exp(R, u)
    return R


def _move_increment(R, factors, xis, h):
    """``R exp(u_1) ... exp(u_m) - R`` as ``R M`` with ``M = prod(I + E_i) - I`` built
    from ``E_i = exp(u_i) - I`` (small when the step is small: no rounding near 1)."""
    M = None
    for alpha in factors:
        u = lincomb(alpha, xis, h)
        if u is None:
            continue
        E = _expm1(u)
        M = E if M is None else M + E + _mm(M, E)
    return jnp.zeros_like(R) if M is None else _mm(R, M)


class CommutatorFree(AbstractLieSolver):
    """A commutator-free Lie-group method over a `CFTableau`.

    **Arguments:**

    - `tableau`: a `CFTableau`.
    """

    tableau: CFTableau = eqx.field(static=True)

    @property
    def order(self) -> int:
        return self.tableau.order

    def _stages(self, scene, t, y, h):
        """Body velocities and vector derivatives of every stage."""
        tab = self.tableau
        xis, dxs = [], []
        for i in range(len(tab.c)):
            if i == 0:
                Yi = y
            else:
                R = _move(y.R, tab.stages[i - 1], xis, h)
                dx = lincomb(tab.vector_a(i), dxs, h)
                Yi = LieState(R, y.x if dx is None else y.x + dx)
            f = scene.vector_field(t + tab.c[i] * h, Yi)
            xis.append(f.xi)
            dxs.append(f.dx)
        return xis, dxs

    def step(self, scene, t, y, h):
        tab = self.tableau
        xis, dxs = self._stages(scene, t, y, h)
        R1 = _move(y.R, tab.final, xis, h)
        dx = lincomb(tab.vector_b, dxs, h)
        return LieState(R1, y.x if dx is None else y.x + dx), jnp.array(False)

    def increment(self, scene, t, y, h):
        tab = self.tableau
        xis, dxs = self._stages(scene, t, y, h)
        dR = _move_increment(y.R, tab.final, xis, h)
        dx = lincomb(tab.vector_b, dxs, h)
        return dR, y.x if dx is None else y.x + dx, jnp.array(False)


F = lambda *xs: tuple(xs)  # noqa: E731

#: Lie–Euler: ``R1 = R0 exp(h Omega0)`` (order 1).
LIE_EULER_TABLEAU = CFTableau.from_fractions(stages=[], final=[F(1)], c=F(0), order=1)

#: Crouch–Grossman, order 3 (Crouch & Grossman 1993, as tabulated by Owren &
#: Marthinsen 1999).
CG3_TABLEAU = CFTableau.from_fractions(
    stages=[[F("3/4")], [F("119/216", 0), F(0, "17/108")]],
    final=[F("13/51", 0, 0), F(0, "-2/3", 0), F(0, 0, "24/17")],
    c=F(0, "3/4", "17/24"),
    order=3,
)

#: Celledoni–Marthinsen–Owren CF4 (2003), order 4, two exponentials in the update.
CF4_TABLEAU = CFTableau.from_fractions(
    stages=[
        [F("1/2")],
        [F(0, "1/2")],
        [F("1/2", 0, 0), F("-1/2", 0, 1)],
    ],
    final=[F("1/4", "1/6", "1/6", "-1/12"), F("-1/12", "1/6", "1/6", "1/4")],
    c=F(0, "1/2", "1/2", 1),
    order=4,
)


class LieEuler(CommutatorFree):
    """Lie–Euler: ``R_{n+1} = R_n exp(h Omega_n)``, explicit Euler for the rest (order 1)."""

    tableau: CFTableau = eqx.field(static=True, default=LIE_EULER_TABLEAU)


class CG3(CommutatorFree):
    """Crouch–Grossman method of order 3 (three stages, three exponentials)."""

    tableau: CFTableau = eqx.field(static=True, default=CG3_TABLEAU)


class CF4(CommutatorFree):
    """Commutator-free method of order 4 of Celledoni, Marthinsen & Owren (2003)."""

    tableau: CFTableau = eqx.field(static=True, default=CF4_TABLEAU)
