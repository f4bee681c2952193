"""Lie-group methods as diffrax solvers: adaptive RKMK pairs and any fixed-step method.

The diffrax state is the scene's `LieState` ``(R, x)`` and the term is a
`LieTerm`, a `diffrax.ODETerm` whose vector field returns a `LieTangent` (body
velocities; see `lie_term`). The solver reads the tangent as ``R' = R hat(xi)``; diffrax
never adds it to the state itself, so every rotation stays on SO(3) to
round-off, at step ends and at interpolated save times alike.

A step of an RKMK method is a classical Runge–Kutta step for the algebra
curve ``u(s)`` with ``R(t0 + s) = R0 exp(u(s))``, ``u' = dexp^-1_u(xi)``,
``u(0) = 0`` (Munthe-Kaas 1999). So the embedded error estimate and the dense
output are the classical ones, taken in the algebra:

- error: ``e = u_high - u_low = h sum_j (b_j - b^_j) K~_j`` for the rotations,
  ``h sum_j (b_j - b^_j) dx_j`` for the vector part;
- dense output: ``R(t0 + theta h) = R0 exp(p(theta))`` with ``p`` the continuous
  extension polynomial of the pair in the algebra (never a blend of matrices).

References: H. Munthe-Kaas, "High order Runge–Kutta methods on manifolds",
Appl. Numer. Math. 29 (1999) 115–127; A. Marthinsen, "Interpolation in Lie
groups", SIAM J. Numer. Anal. 37 (1999) 269–285 (dense output in the algebra);
L. F. Shampine, "Some practical Runge–Kutta formulas", Math. Comp. 46 (1986)
135–150 (the Dormand–Prince midpoint weights).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from fractions import Fraction
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._scene import Scene
from .._so3 import _dcayinv, _dexpinv, _hat, _log_from_quat, _mm, _mT, _to_quat
from .._state import LieState, LieTangent, retract
from .._types import Array
from ._base import AbstractLieSolver, ButcherTableau, lincomb
from ._cf import CommutatorFree
from ._rkmk import DOPRI5_TABLEAU, RKMK, RKMK45, rkmk_stages_looped

# --------------------------------------------------------------------------
# The term
# --------------------------------------------------------------------------


class SceneVectorField(eqx.Module):
    """A scene's vector field in diffrax's ``(t, y, args)`` form (returns a `LieTangent`).

    A module rather than a closure, so the scene's arrays (gains, inertia) are
    pytree leaves that `jax.grad` and `eqx.filter_*` see.
    """

    scene: Scene

    def __call__(self, t, y: LieState, args) -> LieTangent:
        del args
        return self.scene.vector_field(t, y)


class LieTerm(diffrax.ODETerm):
    """A diffrax ODE term on ``SO(3)^k x R^n`` whose vector field returns a `LieTangent`.

    ``R_i' = R_i hat(xi_i)``, ``x' = dx`` with ``(xi, dx) = vector_field(t, y, args)``.
    Unlike a plain `diffrax.ODETerm` (whose output must be shaped like ``y``), the
    output is a tangent in body form; only the so3jax solvers of `diffrax_solver`
    read it, and they never add it to the state, so rotations stay rotations.

    **Arguments:**

    - `vector_field`: ``(t, y: LieState, args) -> LieTangent``.
    """

    def vf(self, t, y: LieState, args) -> LieTangent:
        return _check_tangent(self.vector_field(t, y, args), y)

    def prod(self, vf: LieTangent, control) -> LieTangent:
        return jax.tree.map(lambda v: control * v, vf)


def lie_term(scene: Scene) -> LieTerm:
    """The diffrax term of a scene, for the solvers of `diffrax_solver`.

    ``y' = f(t, y)`` on ``SO(3)^k x R^n`` with ``f`` returning a `LieTangent`
    (``R_i' = R_i hat(xi_i)``, ``x' = dx``).

    **Arguments:**

    - `scene`: a so3jax scene (e.g. `scenes.free_body(...)`).

    **Returns:** a `LieTerm`; pass it with ``y0=scene.y0`` to
    `diffrax.diffeqsolve` together with a solver from `diffrax_solver`.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a so3jax scene, got {type(scene).__name__}")
    return LieTerm(SceneVectorField(scene))


class _TermScene(eqx.Module):
    """The `vector_field` protocol of a scene, read from a diffrax term.

    Lets the `AbstractLieSolver` steps (which call ``scene.vector_field``) run
    on any term, including diffrax's time-reversing `WrapTerm`.
    """

    terms: Any
    args: Any

    def vector_field(self, t, y: LieState) -> LieTangent:
        return self.terms.vf(t, y, self.args)


def _unwrap_scene(terms) -> Scene | None:
    term = terms
    # diffrax wraps the term (time direction) in a module with a `.term` field.
    while not isinstance(term, LieTerm) and isinstance(getattr(term, "term", None), LieTerm):
        term = term.term
    if isinstance(term, LieTerm) and isinstance(term.vector_field, SceneVectorField):
        return term.vector_field.scene
    return None


def _check_tangent(f, y: LieState) -> LieTangent:
    if not isinstance(f, LieTangent):
        raise ValueError(
            "the term's vector field must return a so3jax.LieTangent (body velocities "
            f"xi and dx), got {type(f).__name__}; build the term with so3jax.lie_term(scene) "
            "or so3jax.LieTerm(fn)"
        )
    if f.xi.shape != y.R.shape[:-1] or f.dx.shape != y.x.shape:
        raise ValueError(
            f"the vector field returned xi {f.xi.shape} and dx {f.dx.shape}, expected "
            f"{y.R.shape[:-1]} and {y.x.shape} to match y0 = LieState(R {y.R.shape}, "
            f"x {y.x.shape})"
        )
    return f


def _check_state(y) -> LieState:
    if not isinstance(y, LieState):
        raise ValueError(f"y0 must be a so3jax.LieState (e.g. scene.y0), got {type(y).__name__}")
    return y


def _ambient(y: LieState, f: LieTangent) -> LieState:
    """``(R hat(xi), dx)``: the tangent in the ambient space, shaped like ``y``."""
    return LieState(_mm(y.R, _hat(f.xi)), f.dx)


# --------------------------------------------------------------------------
# Dense output in the algebra
# --------------------------------------------------------------------------


class LieInterpolation(diffrax.AbstractLocalInterpolation):
    """Dense output of one step that moves along the group.

    ``R(t0 + theta h) = R0 exp(p_u(theta))``, ``x(t0 + theta h) = p_x(theta)``
    with polynomials in ``theta = (t - t0) / (t1 - t0)`` (highest power first;
    ``p_u(0) = 0``).

    **Fields:**

    - `t0`, `t1`: the step.
    - `R0`: rotations at ``t0``, shape `(k, 3, 3)`.
    - `cu`: coefficients of ``p_u``, shape `(m, k, 3)` (no constant term).
    - `cx`: coefficients of ``p_x``, shape `(m + 1, n)`.
    - `coords`: ``"exp"`` (``R0 exp(p_u)``) or ``"cayley"`` (``R0 cay(p_u)``: the
      coordinates of an RKMK method in Cayley coordinates).
    """

    t0: Any
    t1: Any
    R0: Array
    cu: Array
    cx: Array
    coords: str = eqx.field(static=True, default="exp")

    def _at(self, t) -> LieState:
        # An empty step (t0 == t1: a lane of a vmapped run that has finished, stepping
        # on while others go on) would divide 0 by 0: its NaN is selected away in the
        # value but poisons reverse mode (0 times NaN), as diffrax's linear_rescale knows.
        empty = self.t1 == self.t0
        theta = (t - self.t0) / jnp.where(empty, 1, self.t1 - self.t0)
        theta = jnp.asarray(jnp.where(empty, 0, theta), self.cu.dtype)
        u = jnp.zeros_like(self.cu[0])
        for c in self.cu:
            u = (u + c) * theta
        x = jnp.zeros_like(self.cx[0])
        for c in self.cx:
            x = x * theta + c
        return retract(LieState(self.R0, jnp.zeros_like(x)), u, x, self.coords)

    def evaluate(self, t0, t1=None, left: bool = True):
        del left
        if t1 is None:
            return self._at(t0)
        return jax.tree.map(lambda a, b: a - b, self._at(t1), self._at(t0))


def _hermite3(y1, f0, f1):
    """Coefficients ``(a, b, c)`` of ``a s^3 + b s^2 + c s`` with p(0) = 0, p'(0) = f0,
    p(1) = y1, p'(1) = f1 (cubic Hermite; increments already scaled by h)."""
    A = y1 - f0
    B = f1 - f0
    return jnp.stack([B - 2 * A, 3 * A - B, f0])


def _quartic(y1, ymid, f0, f1):
    """Coefficients ``(a, b, c, d)`` of ``a s^4 + b s^3 + c s^2 + d s`` with p(0) = 0,
    p'(0) = f0, p(1/2) = ymid, p(1) = y1, p'(1) = f1."""
    A = y1 - f0  # a + b + c
    B = f1 - f0  # 4a + 3b + 2c
    C = ymid - 0.5 * f0  # a/16 + b/8 + c/4
    a = 16 * C - 8 * A + 2 * B
    b = B - 2 * A - 2 * a
    c = A - a - b
    return jnp.stack([a, b, c, f0])


def _with_const(coeffs, y0):
    return jnp.concatenate([coeffs, y0[None]])


def _F(*xs) -> np.ndarray:
    return np.array([float(Fraction(x)) for x in xs])


# Weights of y(t0 + h/2) = y0 + h sum_j w_j K_j for the Dormand–Prince 5(4) pair,
# a fourth-order continuous extension at the midpoint (Shampine 1986, sec. 5).
_MIDPOINT_WEIGHTS: dict[ButcherTableau, np.ndarray] = {
    DOPRI5_TABLEAU: 0.5
    * _F(
        "6025192743/30085553152",
        0,
        "51252292925/65400821598",
        "-2691868925/45128329728",
        "187940372067/1594534317056",
        "-1776094331/19743644256",
        "11237099/235043384",
    )
}


#: Tsitouras 5(4) (Comput. Math. Appl. 62 (2011) 770–775, table 1), FSAL. Same cost per
#: step as Dormand–Prince 5(4), smaller error constants: fewer steps at equal accuracy.
TSIT5_TABLEAU = ButcherTableau(
    a=(
        (0.161,),
        (-0.008480655492356989, 0.335480655492357),
        (2.8971530571054935, -6.359448489975075, 4.3622954328695815),
        (5.325864828439257, -11.748883564062828, 7.4955393428898365, -0.09249506636175525),
        (
            5.86145544294642,
            -12.92096931784711,
            8.159367898576159,
            -0.071584973281401,
            -0.028269050394068383,
        ),
        (
            0.09646076681806523,
            0.01,
            0.4798896504144996,
            1.379008574103742,
            -3.290069515436081,
            2.324710524099774,
        ),
    ),
    b=(
        0.09646076681806523,
        0.01,
        0.4798896504144996,
        1.379008574103742,
        -3.290069515436081,
        2.324710524099774,
        0.0,
    ),
    c=(0.0, 0.161, 0.327, 0.9, 0.9800255409045097, 1.0, 1.0),
    order=5,
    b_low=(
        0.09468075576583945,
        0.009183565540343254,
        0.4877705284247616,
        1.234297566930479,
        -2.7077123499835256,
        1.866628418170587,
        0.015151515151515152,
    ),
    order_low=4,
    fsal=True,
)


class RKMKTsit5(RKMK45):
    """RKMK with the Tsitouras 5(4) pair and the exact dexp^-1 (order 5).

    Seven stages (FSAL) like `RKMK45`, with smaller error constants: the
    adaptive Lie-group method that takes the fewest steps at a given accuracy.
    ``RKMKTsit5(embedded=True)`` steps with the order-4 weights.

    References: Ch. Tsitouras, "Runge–Kutta pairs of order 5(4) satisfying only
    the first column simplifying assumption", Comput. Math. Appl. 62 (2011) 770–775.
    """

    tableau: ButcherTableau = eqx.field(static=True, default=TSIT5_TABLEAU)


def _dense_rkmk(tableau: ButcherTableau, y0: LieState, u1, dx1, kts, dxs, h) -> dict:
    """Dense info of an FSAL RKMK step: quartic (midpoint weights known) or cubic Hermite."""
    f0u, f1u = h * kts[0], h * kts[-1]
    f0x, f1x = h * dxs[0], h * dxs[-1]
    w = _MIDPOINT_WEIGHTS.get(tableau)
    if w is None:
        cu = _hermite3(u1, f0u, f1u)
        cx = _hermite3(dx1, f0x, f1x)
    else:
        umid = lincomb(tuple(w), kts, h)
        xmid = lincomb(tuple(w), dxs, h)
        cu = _quartic(u1, umid, f0u, f1u)
        cx = _quartic(dx1, xmid, f0x, f1x)
    return dict(R0=y0.R, cu=cu, cx=_with_const(cx, y0.x))


# --------------------------------------------------------------------------
# Solvers
# --------------------------------------------------------------------------


def _made_jump_select(made_jump, fresh: Callable, stored):
    if made_jump is False:
        return stored
    return jax.lax.cond(made_jump, fresh, lambda: stored)


class DiffraxLieAdaptiveSolver(diffrax.AbstractAdaptiveSolver):
    """An embedded RKMK pair as an adaptive diffrax solver.

    Each step is ``R1 = R0 exp(u_high)``, ``x1 = x0 + dx_high`` with the
    higher-order weights (local extrapolation, FSAL), and the error estimate is
    taken in the Lie algebra: ``e = u_high - u_low`` (body frame, radians). It is
    returned as ``LieState(R0 hat(e), dx_high - dx_low)``: a pytree shaped like
    ``y``, as diffrax's controllers need, whose rotation leaf is the first-order
    image in the ambient space of the algebra error (``R0 exp(u + e) - R0 exp(u) =
    R0 hat(e) + O(|u| |e| + |e|^2)``, and ``|R0 hat(e)|_F = sqrt(2) |e|``). So
    ``PIDController(rtol, atol)`` means what it means for an ambient solver on
    ``R^9k x R^n``, and tolerances compare directly with diffrax's solvers on the
    embedded system.

    Build it with `diffrax_solver` (``diffrax_solver(RKMK45())``).

    **Arguments:**

    - `method`: an `RKMK` whose tableau has embedded weights (`RKMK45`, `RKMKTsit5`,
      `RKMK32`).

    References: H. Munthe-Kaas, Appl. Numer. Math. 29 (1999) 115–127; A. Iserles,
    H. Munthe-Kaas, S. Nørsett, A. Zanna, "Lie-group methods", Acta Numer. 9
    (2000) 215–365, sec. 6 (embedded pairs and error estimates in the algebra).
    """

    method: RKMK

    term_structure: ClassVar = LieTerm

    @property
    def interpolation_cls(self) -> Callable[..., LieInterpolation]:  # pyright: ignore
        # Dense output in the method's own coordinates (exp or Cayley).
        return functools.partial(LieInterpolation, coords=self.method.coords)

    def __check_init__(self):
        if not isinstance(self.method, RKMK) or self.method.tableau.b_low is None:
            raise ValueError(
                "method must be an RKMK method with an embedded pair (so3jax.RKMK45() or "
                f"so3jax.RKMK32()), got {self.method!r}"
            )

    def order(self, terms) -> int:
        return self.method.tableau.order

    def init(self, terms, t0, t1, y0, args) -> LieTangent | None:
        y0 = _check_state(y0)
        f0 = _check_tangent(terms.vf(t0, y0, args), y0)
        return f0 if self.method.tableau.fsal else None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        tab = self.method.tableau
        exact = self.method.dexpinv == "exact"
        h = terms.contr(t0, t1)
        if tab.fsal:
            f0 = _made_jump_select(made_jump, lambda: terms.vf(t0, y0, args), solver_state)
        else:
            f0 = None
        coords = self.method.coords
        scene = _TermScene(terms, args)
        if f0 is None:  # (not FSAL: the first stage is evaluated here, the rest in a loop)
            f0 = terms.vf(t0, y0, args)
        kts, dxs, f_last = rkmk_stages_looped(tab, exact, scene, t0, y0, h, f0, coords)
        u1 = lincomb(tab.b, kts, h)
        dx1 = lincomb(tab.b, dxs, h)
        db = tuple(hi - lo for hi, lo in zip(tab.b, tab.b_low, strict=True))
        eu = lincomb(db, kts, h)
        ex = lincomb(db, dxs, h)
        y1 = retract(y0, u1, dx1, coords)
        y_error = LieState(_mm(y0.R, _hat(eu)), ex)
        if tab.fsal:
            dense_info = _dense_rkmk(tab, y0, u1, dx1, kts, dxs, h)
            return y1, y_error, dense_info, f_last, diffrax.RESULTS.successful
        # No FSAL: the end slope costs one more evaluation (removed unless a save needs it).
        f1 = terms.vf(t1, y1, args)
        dinv = _dcayinv if coords == "cayley" else _dexpinv
        cu = _hermite3(u1, h * kts[0], h * dinv(u1, f1.xi))
        cx = _hermite3(dx1, h * dxs[0], h * f1.dx)
        dense_info = dict(R0=y0.R, cu=cu, cx=_with_const(cx, y0.x))
        return y1, y_error, dense_info, None, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args) -> LieState:
        """The ambient velocity ``(R hat(xi), dx)`` (diffrax's initial-step heuristic)."""
        return _ambient(y0, terms.vf(t0, y0, args))


class DiffraxLieSolver(diffrax.AbstractSolver):
    """Any fixed-step so3jax method (`AbstractLieSolver`) as a diffrax solver.

    No error estimate: use it with `diffrax.ConstantStepSize` (or
    `diffrax.StepTo`). Dense output is the cubic Hermite interpolant in the
    algebra, ``R(t0 + theta h) = R0 exp(p(theta))`` with ``p(1) = log(R0^T R1)``
    and end slopes from the vector field at both ends (evaluated only when a
    save needs them: unused, they are removed by the compiler).

    Methods that need more than the vector field (`LGVI` uses the body and the
    torque) get the scene inside the `lie_term`; with such a method integrate
    forward in time (``t1 > t0``).

    **Arguments:**

    - `method`: an `AbstractLieSolver` (e.g. `RKMK4()`, `CG3()`, `LGVI()`).
    """

    method: AbstractLieSolver

    term_structure: ClassVar = LieTerm
    interpolation_cls: ClassVar[Callable[..., LieInterpolation]] = LieInterpolation

    def __check_init__(self):
        if not isinstance(self.method, AbstractLieSolver):
            raise ValueError(
                f"method must be a so3jax Lie-group method (e.g. RKMK4()), got {self.method!r}"
            )

    def order(self, terms) -> int:
        return self.method.order

    def init(self, terms, t0, t1, y0, args) -> None:
        _check_tangent(terms.vf(t0, _check_state(y0), args), y0)
        return None

    def _scene(self, terms, args):
        # RKMK and commutator-free steps only call `vector_field`: read it from the
        # term (right under diffrax's time reversal). Others get the scene itself.
        if isinstance(self.method, (RKMK, CommutatorFree)):
            return _TermScene(terms, args)
        scene = _unwrap_scene(terms)
        return _TermScene(terms, args) if scene is None else scene

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        h = terms.contr(t0, t1)
        y1, failed = self.method.step(self._scene(terms, args), t0, y0, h)
        result = diffrax.RESULTS.where(
            failed, diffrax.RESULTS.nonlinear_divergence, diffrax.RESULTS.successful
        )
        # Cubic Hermite dense output in the algebra (dead code unless saved at ts).
        u1 = _log_from_quat(_to_quat(_mm(_mT(y0.R), y1.R)))
        f0 = terms.vf(t0, y0, args)
        f1 = terms.vf(t1, y1, args)
        cu = _hermite3(u1, h * f0.xi, h * _dexpinv(u1, f1.xi))
        cx = _hermite3(y1.x - y0.x, h * f0.dx, h * f1.dx)
        dense_info = dict(R0=y0.R, cu=cu, cx=_with_const(cx, y0.x))
        return y1, None, dense_info, None, result

    def func(self, terms, t0, y0, args) -> LieState:
        """The ambient velocity ``(R hat(xi), dx)``."""
        return _ambient(y0, terms.vf(t0, y0, args))


def diffrax_solver(method: AbstractLieSolver) -> DiffraxLieSolver | DiffraxLieAdaptiveSolver:
    """A so3jax Lie-group method as a `diffrax` solver.

    ``diffeqsolve(lie_term(scene), diffrax_solver(RKMK45()), t0, t1, dt0,
    scene.y0, stepsize_controller=PIDController(rtol, atol), saveat=...)``
    integrates on ``SO(3)^k x R^n``: every rotation stays on the group, also at
    interpolated save times.

    **Arguments:**

    - `method`: `RKMK45()`, `RKMKTsit5()` or `RKMK32()` (embedded pairs: an adaptive solver with
      the error estimate in the Lie algebra), or any other `AbstractLieSolver`
      (fixed step: use `diffrax.ConstantStepSize`). ``RKMK45(embedded=True)``
      gives the fixed-step lower-order member.

    **Returns:** a `DiffraxLieAdaptiveSolver` or a `DiffraxLieSolver`.
    """
    if not isinstance(method, AbstractLieSolver):
        raise ValueError(
            f"method must be a so3jax Lie-group method (e.g. so3jax.RKMK45()), got {method!r}"
        )
    tab = getattr(method, "tableau", None)
    if (
        isinstance(method, RKMK)
        and isinstance(tab, ButcherTableau)
        and tab.b_low is not None
        and not getattr(method, "embedded", False)
    ):
        return DiffraxLieAdaptiveSolver(method)
    return DiffraxLieSolver(method)
