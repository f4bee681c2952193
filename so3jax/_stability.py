"""Step-size limits of the fixed-step methods under the geometric controller.

An explicit Runge–Kutta step applied to ``y' = lambda y`` multiplies ``y`` by
its stability polynomial ``P(z)``, ``z = h lambda``:

    P(z) = 1 + sum_k z^k b^T A^(k-1) 1

and the step is stable when ``|P(h lambda)| <= 1``. The attitude methods share
this with their vector part (RKMK: the Butcher tableau; commutator-free
methods: the summed coefficients), so near a steady state they are stable
exactly where the plain Runge–Kutta method is.

The closed loop of the geometric controller, linearised about zero tracking
error (the gyroscopic and feed-forward terms cancel), is per axis

    J e'' + K_Omega e' + K_R e = 0,

with eigenvalues ``(-k_Omega +- sqrt(k_Omega^2 - 4 J k_R)) / (2 J)``; the
fast one, about ``-k_Omega / J_min`` when overdamped, sets the step limit
``h < rho / |lambda|``, ``rho`` the radius of the stability region along the
eigenvalue's direction (on the negative real axis: 2 for Lie–Euler, 2.51 for
the three-stage order-3 methods, 2.79 for RK4-type, 3.31 for Dormand–Prince).
The measured largest stable steps of ``benchmarks/stability.py`` follow this
to within -3 % and +6 % (RKMK4, seed gains: 0.100 s measured, 0.103 s predicted).

LGVI treats the torque by fixed-point iteration, which converges for
``h k_Omega / (2 J_min) < 1``: its limit is ``2 J_min / k_Omega``.

References: E. Hairer, G. Wanner, *Solving Ordinary Differential Equations
II*, 2nd ed., sec. IV.2 (stability functions of explicit RK methods);
T. Lee, M. Leok, N. H. McClamroch, CDC 2010 (the error dynamics).
"""

from __future__ import annotations

import functools

import numpy as np

from ._dynamics import RigidBody
from ._integrators import LGVI, RKMK, AbstractLieSolver, CommutatorFree

#: Interval of absolute stability on the negative real axis, ``|P(-s)| <= 1`` for
#: ``0 <= s <= interval``, by method (rounded down; `stability_interval` computes it
#: from the tableau and tests/test_sweep_outcomes.py checks it against steps of
#: ``y' = lambda y``). LGVI: the fixed-point bound ``h k_Omega / J_min < 2``.
STABILITY_INTERVAL = {
    "LieEuler": 2.0,
    "CG3": 2.512,
    "RKMK32": 2.512,
    "RKMK4": 2.785,
    "CF4": 2.785,
    "RKMK45": 3.306,
    "LGVI": 2.0,
}

#: Default safety factor on the linearised limit (the linearisation ignores the
#: attitude nonlinearity and the reference's feed-forward).
SAFETY = 0.9


def _rk_data(method):
    """``(A, b)`` of the plain Runge–Kutta method the vector part uses, or ``None``."""
    if isinstance(method, RKMK):
        tab = method.tableau
        s = tab.stages
        A = np.zeros((s, s))
        for i, row in enumerate(tab.a, start=1):
            A[i, :i] = row
        return A, np.asarray(method._weights(), float)
    if isinstance(method, CommutatorFree):
        tab = method.tableau
        s = len(tab.c)
        A = np.zeros((s, s))
        for i in range(1, s):
            A[i, :i] = tab.vector_a(i)
        return A, np.asarray(tab.vector_b, float)
    return None


def stability_polynomial(method: AbstractLieSolver) -> np.ndarray | None:
    """Coefficients ``p_k`` of ``P(z) = sum_k p_k z^k`` (lowest first), or ``None``.

    ``P(h lambda)`` is what one step multiplies the solution of ``y' = lambda y``
    by (explicit methods; ``None`` for others, e.g. `LGVI`).
    """
    data = _rk_data(method)
    if data is None:
        return None
    A, b = data
    coeffs = [1.0]
    v = np.ones(len(b))
    for _ in range(len(b)):
        coeffs.append(float(b @ v))
        v = A @ v
    return np.asarray(coeffs)


def _radius(p: np.ndarray, theta: np.ndarray, r_max: float = 8.0, n: int = 8001) -> np.ndarray:
    """First radius along each ray ``z = r e^{i theta}`` where ``|P(z)| > 1``."""
    r = np.linspace(0.0, r_max, n)[1:]
    z = r[None, :] * np.exp(1j * theta)[:, None]
    bad = np.abs(np.polynomial.polynomial.polyval(z, p)) > 1.0 + 1e-12
    first = np.where(bad.any(axis=1), bad.argmax(axis=1), r.size)
    return np.concatenate([[0.0], r])[first]


@functools.lru_cache(maxsize=64)
def _ray_table(coeffs: tuple) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(np.pi / 2, np.pi, 181)
    return theta, _radius(np.asarray(coeffs), theta)


def stability_interval(method: AbstractLieSolver) -> float:
    """Interval of absolute stability on the negative real axis of a method.

    ``|P(-s)| <= 1`` for ``0 <= s <= interval``: a decaying mode ``y' = -a y``
    is integrated stably while ``h a <= interval``. Computed from the tableau
    (2 for `LieEuler`, about 2.51 for `CG3`, 2.79 for `RKMK4`, 3.31 for
    `RKMK45`); for `LGVI` it is 2, in units of the rate ``k_Omega / J_min`` of its
    fixed-point iteration.

    **Arguments:**

    - `method`: a Lie-group method.

    **Returns:** a float, or ``nan`` for a method whose limit is unknown.
    """
    if isinstance(method, LGVI):
        return 2.0
    p = stability_polynomial(method)
    if p is None:
        return float("nan")
    return float(_radius(p, np.array([np.pi]), n=80001)[0])


def closed_loop_eigenvalues(inertia, k_R, k_Omega) -> np.ndarray:
    """Eigenvalues of the linearised error dynamics ``J e'' + K_Omega e' + K_R e = 0``.

    **Arguments:**

    - `inertia`: `(3, 3)` inertia (or 3 principal moments).
    - `k_R`, `k_Omega`: gains, shape `(G,)` or `(G, 3)` (per axis).

    **Returns:** shape `(G, 6)`, complex.
    """
    J = np.asarray(inertia, float)
    if J.shape == (3,):
        J = np.diag(J)
    kR = np.broadcast_to(np.asarray(k_R, float).reshape(len(k_R), -1), (len(k_R), 3))
    kO = np.broadcast_to(np.asarray(k_Omega, float).reshape(len(k_Omega), -1), (len(k_Omega), 3))
    Jinv = np.linalg.inv(J)
    G = kR.shape[0]
    A = np.zeros((G, 6, 6))
    A[:, :3, 3:] = np.eye(3)
    A[:, 3:, :3] = -Jinv[None] * kR[:, None, :]
    A[:, 3:, 3:] = -Jinv[None] * kO[:, None, :]
    return np.linalg.eigvals(A)


def _gain_batch(k, name: str) -> np.ndarray:
    """Gain sets of shape `(G,)` or `(G, 3)` (a scalar is one set), finite."""
    k = np.atleast_1d(np.asarray(k, float))
    if k.ndim > 2 or (k.ndim == 2 and k.shape[1] != 3):
        raise ValueError(
            f"{name} must have shape (G,) or (G, 3) (G gain sets, scalar or per axis), "
            f"got {k.shape}"
        )
    if not np.all(np.isfinite(k)):
        raise ValueError(f"{name} must be finite, got {k}")
    return k


def stable_dt(method: AbstractLieSolver, inertia, k_R, k_Omega, safety: float = SAFETY):
    """Largest step the method takes stably under the geometric controller, per gain pair.

    ``dt_max = safety * min_j rho(arg lambda_j) / |lambda_j|`` over the decaying
    eigenvalues ``lambda_j`` of `closed_loop_eigenvalues` (a growing mode is
    unstable at every step: it sets no limit), ``rho`` the radius of the
    method's stability region along the eigenvalue's direction. `LGVI`:
    ``safety * 2 J_min / max(k_Omega)``.

    **Arguments:**

    - `method`: a Lie-group method.
    - `inertia`: `(3, 3)` inertia (or 3 principal moments).
    - `k_R`, `k_Omega`: gains, shape `(G,)` or `(G, 3)`.
    - `safety`: factor in ``(0, 1]`` on the linearised limit.

    **Returns:** shape `(G,)`; ``inf`` where no mode limits the step, ``nan``
    for a method whose stability region is unknown.
    """
    if not (0 < safety <= 1):
        raise ValueError(f"safety must be in (0, 1], got {safety}")
    k_R, k_O = _gain_batch(k_R, "k_R"), _gain_batch(k_Omega, "k_Omega")
    if k_R.shape[0] != k_O.shape[0]:
        raise ValueError(
            f"k_R and k_Omega must hold the same number of gain sets, got {k_R.shape[0]} "
            f"and {k_O.shape[0]}"
        )
    # A ValueError naming the inertia if it is not one.
    inertia = np.asarray(RigidBody(inertia).inertia, float)
    G = k_R.shape[0]
    if isinstance(method, LGVI):
        J = np.asarray(inertia, float)
        j_min = np.linalg.eigvalsh(np.diag(J) if J.shape == (3,) else J).min()
        k_max = k_O.reshape(G, -1).max(axis=1)
        with np.errstate(divide="ignore"):
            return np.where(k_max > 0, safety * 2.0 * j_min / np.where(k_max > 0, k_max, 1), np.inf)
    p = stability_polynomial(method)
    if p is None:
        return np.full(G, np.nan)
    lam = closed_loop_eigenvalues(inertia, k_R, k_O)
    theta_tab, rho_tab = _ray_table(tuple(p))
    decaying = lam.real < 0
    theta = np.clip(np.angle(np.where(lam.imag >= 0, lam, np.conj(lam))), np.pi / 2, np.pi)
    # Conservative interpolation: the smaller radius of the two neighbouring rays.
    k = np.clip(np.searchsorted(theta_tab, theta), 1, theta_tab.size - 1)
    rho = np.minimum(rho_tab[k - 1], rho_tab[k])
    with np.errstate(divide="ignore"):
        h = np.where(decaying, rho / np.abs(np.where(decaying, lam, 1.0)), np.inf)
    return safety * h.min(axis=1)
