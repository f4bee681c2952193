"""Runge–Kutta–Munthe-Kaas methods over any explicit tableau.

Stage ``i`` moves to ``R0 exp(u_i)`` with ``u_i = h sum_j a_ij K~_j``, where
``K~_j = dexp^-1_{u_j}(xi_j)`` pulls the body velocity ``xi_j`` of stage ``j``
back to the Lie algebra at ``R0``. For ``R = R0 exp(u)`` and ``R' = R hat(xi)``,
``u' = J_r^-1(u) xi = xi + 1/2 u x xi + D(|u|) u x (u x xi)`` (right
trivialisation: the ``+1/2`` sign matters; the left-trivialised sign keeps the
method on the group but silently drops it to order 2).

References: H. Munthe-Kaas, "High order Runge–Kutta methods on manifolds",
Appl. Numer. Math. 29 (1999); E. Hairer, C. Lubich, G. Wanner, *Geometric
Numerical Integration*, 2nd ed., sec. IV.8.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._engine.passes.cuts import array_cut, array_cut_index, derivative_cut
from .._so3 import _D_SERIES, _FULL, _cross, _dcayinv, _dexpinv, _dot, _polyval
from .._state import LieState, advance, increment, retract
from ._base import AbstractLieSolver, ButcherTableau, lincomb


def _dexpinv_truncated(u, v, order: int):
    """``J_r^-1(u) v`` truncated to the commutators needed for ``order``.

    Terms of degree ``q <= order - 2`` in ``u`` suffice (Munthe-Kaas 1999).
    """
    if order <= 2:
        return v
    uxv = _cross(u, v)
    out = v + 0.5 * uxv
    n_terms = (order - 2) // 2
    if n_terms > 0:
        D = _polyval(_D_SERIES[:n_terms], _dot(u, u))[..., None]
        out = out + D * _cross(u, uxv)
    return out


def _pull_back(u, xi, exact: bool, order: int, coords: str):
    """A stage's body velocity ``xi`` pulled back to the algebra at ``R0`` (``u != 0``)."""
    if coords == "cayley":
        return _dcayinv(u, xi)
    if exact:
        return _dexpinv(u, xi)
    return _dexpinv_truncated(u, xi, order)


def _consumers(tableau: ButcherTableau, j: int) -> int:
    """How many later stages and weights read stage ``j`` (nonzero tableau entries)."""
    rows = [row for row in tableau.a[j:] if len(row) > j]
    return sum(1 for row in rows if row[j] != 0) + int(tableau.b[j] != 0)


def rkmk_stages(
    tableau: ButcherTableau,
    exact: bool,
    scene,
    t,
    y: LieState,
    h,
    f0=None,
    return_last=False,
    coords: str = "exp",
):
    """Run the stages; return the pulled-back velocities and vector derivatives.

    ``f0`` (a `LieTangent` at ``(t, y)``) replaces the first evaluation (FSAL);
    with ``return_last`` the raw `LieTangent` of the last stage is returned too.
    ``coords="cayley"`` uses the Cayley map and its exact ``dcay^-1`` (``exact``
    is then ignored).
    """
    order = tableau.order
    kts, dxs = [], []
    for i in range(tableau.stages):
        if i == 0:
            Yi, u = y, None
        else:
            row = tableau.a[i - 1]
            u = lincomb(row, kts, h)
            dx = lincomb(row, dxs, h)
            u = jnp.zeros_like(y.R[..., 0]) if u is None else u
            dx = jnp.zeros_like(y.x) if dx is None else dx
            Yi = retract(y, u, dx, coords)
        if i == 0 and f0 is not None:
            f = f0
        else:
            f = scene.vector_field(t + tableau.c[i] * h, Yi)
        kt = f.xi if u is None else _pull_back(u, f.xi, exact, order, coords)
        # A stage feeds later ones: materialized, or XLA recomputes it, dexp^-1 and
        # vector field included, in each (`array_cut_index`). A stage with two
        # consumers (RK4's) pays for a cut only in the derivative programs
        # (`derivative_cut`).
        if _consumers(tableau, i) >= 3:
            kt, dx = array_cut(array_cut_index(kt), kt, f.dx)
        else:
            kt, dx = derivative_cut(kt, f.dx)
        kts.append(kt)
        dxs.append(dx)
    if return_last:
        return kts, dxs, f
    return kts, dxs


def rkmk_stages_looped(
    tableau: ButcherTableau, exact: bool, scene, t, y: LieState, h, f0, coords: str = "exp"
):
    """`rkmk_stages` with stages ``1 .. s-1`` as one loop (`jax.lax.fori_loop`).

    Returns ``(kts, dxs, f_last)`` like ``rkmk_stages(..., f0=f0, return_last=True)``,
    to round-off: the stage sums run over the whole row of ``a`` (zeros included)
    instead of its nonzero entries. The vector field, the retraction and
    ``dexp^-1`` are traced once instead of once per stage, as diffrax does for its
    own Runge–Kutta solvers. The adaptive solvers use it: their step sits inside
    diffrax's loops, which a reverse-mode gradient (`diffrax.RecursiveCheckpointAdjoint`)
    traces and compiles several times, so one traced stage compiles faster and runs
    no slower (``benchmarks/adaptive_compile.py``). The fixed-step methods keep the
    unrolled stages: the scalarized program has no loops.
    """
    s = tableau.stages
    dtype = y.R.dtype
    A = np.zeros((s, s))
    for i, row in enumerate(tableau.a, start=1):
        A[i, :i] = row
    A = jnp.asarray(A, dtype)
    c = jnp.asarray(tableau.c, dtype)
    K = jnp.zeros((s,) + y.R.shape[:-1], dtype).at[0].set(f0.xi)
    DX = jnp.zeros((s,) + y.x.shape, y.x.dtype).at[0].set(f0.dx)

    def stage(i, carry):
        K, DX, _ = carry
        u = h * jnp.tensordot(A[i], K, axes=1, precision=_FULL)
        dx = h * jnp.tensordot(A[i].astype(DX.dtype), DX, axes=1, precision=_FULL)
        f = scene.vector_field(t + c[i] * h, retract(y, u, dx, coords))
        kt = _pull_back(u, f.xi, exact, tableau.order, coords)
        return K.at[i].set(kt), DX.at[i].set(f.dx), f

    K, DX, f = jax.lax.fori_loop(1, s, stage, (K, DX, f0))
    return [K[i] for i in range(s)], [DX[i] for i in range(s)], f


class RKMK(AbstractLieSolver):
    """Runge–Kutta–Munthe-Kaas method over an explicit `ButcherTableau`.

    ``R_{n+1} = R_n exp(h sum_i b_i dexp^-1_{u_i}(Omega_i))``; the vector part is
    the plain RK update.

    **Arguments:**

    - `tableau`: a `ButcherTableau`.
    - `dexpinv`: ``"exact"`` (the right Jacobian inverse) or ``"truncated"``
      (the series cut at the commutators the order needs: cheaper, same order).
    - `coords`: ``"exp"`` (exponential coordinates, ``R = R0 exp(u)``) or
      ``"cayley"`` (``R = R0 cay(u)`` with the Cayley map and its exact, rational
      ``dcay^-1``: same order, no trigonometric functions or small-angle
      branches, so cheaper per step; `dexpinv` is then ignored).

    References: H. Munthe-Kaas, Appl. Numer. Math. 29 (1999) 115–127; A.
    Iserles, H. Munthe-Kaas, S. Nørsett, A. Zanna, Acta Numer. 9 (2000)
    215–365, sec. 8.3 (the Cayley map as coordinates).
    """

    tableau: ButcherTableau = eqx.field(static=True)
    dexpinv: str = eqx.field(static=True, default="exact")
    coords: str = eqx.field(static=True, default="exp")

    def __check_init__(self):
        if self.dexpinv not in ("exact", "truncated"):
            raise ValueError(f"dexpinv must be 'exact' or 'truncated', got {self.dexpinv!r}")
        if self.coords not in ("exp", "cayley"):
            raise ValueError(f"coords must be 'exp' or 'cayley', got {self.coords!r}")

    @property
    def order(self) -> int:
        return self.tableau.order

    def step(self, scene, t, y, h):
        u, dx = self._update(scene, t, y, h)
        return advance(y, u, dx, self.coords), jnp.array(False)

    def _weights(self):
        return self.tableau.b

    def _update(self, scene, t, y, h):
        """The step's algebra element ``u`` (``R1 = R0 exp(u)``) and the change of ``y.x``."""
        kts, dxs = rkmk_stages(
            self.tableau, self.dexpinv == "exact", scene, t, y, h, coords=self.coords
        )
        b = self._weights()
        return lincomb(b, kts, h), lincomb(b, dxs, h)

    def increment(self, scene, t, y, h):
        u, dx = self._update(scene, t, y, h)
        return increment(y.R, u, self.coords), y.x + dx, jnp.array(False)


F = lambda *xs: tuple(xs)  # noqa: E731  (short rows for the tableaus below)

#: The classic Runge–Kutta tableau (order 4).
RK4_TABLEAU = ButcherTableau.from_fractions(
    a=[F("1/2"), F(0, "1/2"), F(0, 0, 1)],
    b=F("1/6", "1/3", "1/3", "1/6"),
    c=F(0, "1/2", "1/2", 1),
    order=4,
)

#: Dormand–Prince 5(4) (J. Comput. Appl. Math. 6, 1980), FSAL.
DOPRI5_TABLEAU = ButcherTableau.from_fractions(
    a=[
        F("1/5"),
        F("3/40", "9/40"),
        F("44/45", "-56/15", "32/9"),
        F("19372/6561", "-25360/2187", "64448/6561", "-212/729"),
        F("9017/3168", "-355/33", "46732/5247", "49/176", "-5103/18656"),
        F("35/384", 0, "500/1113", "125/192", "-2187/6784", "11/84"),
    ],
    b=F("35/384", 0, "500/1113", "125/192", "-2187/6784", "11/84", 0),
    c=F(0, "1/5", "3/10", "4/5", "8/9", 1, 1),
    order=5,
    b_low=F("5179/57600", 0, "7571/16695", "393/640", "-92097/339200", "187/2100", "1/40"),
    order_low=4,
    fsal=True,
)

#: Bogacki–Shampine 3(2) (Appl. Math. Lett. 2, 1989), FSAL.
BS3_TABLEAU = ButcherTableau.from_fractions(
    a=[F("1/2"), F(0, "3/4"), F("2/9", "1/3", "4/9")],
    b=F("2/9", "1/3", "4/9", 0),
    c=F(0, "1/2", "3/4", 1),
    order=3,
    b_low=F("7/24", "1/4", "1/3", "1/8"),
    order_low=2,
    fsal=True,
)


class RKMK4(RKMK):
    """RKMK with the classic RK4 tableau and dexp^-1 truncated at order 4 (order 4)."""

    tableau: ButcherTableau = eqx.field(static=True, default=RK4_TABLEAU)
    dexpinv: str = eqx.field(static=True, default="truncated")


class RKMK45(RKMK):
    """RKMK with the Dormand–Prince 5(4) pair and the exact dexp^-1 (order 5).

    ``RKMK45(embedded=True)`` steps with the order-4 embedded weights instead.
    """

    tableau: ButcherTableau = eqx.field(static=True, default=DOPRI5_TABLEAU)
    dexpinv: str = eqx.field(static=True, default="exact")
    embedded: bool = eqx.field(static=True, default=False)

    @property
    def order(self) -> int:
        return self.tableau.order_low if self.embedded else self.tableau.order

    def _weights(self):
        return self.tableau.b_low if self.embedded else self.tableau.b


class RKMK32(RKMK45):
    """RKMK with the Bogacki–Shampine 3(2) pair and the exact dexp^-1 (order 3)."""

    tableau: ButcherTableau = eqx.field(static=True, default=BS3_TABLEAU)
