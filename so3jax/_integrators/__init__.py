"""Lie-group integrators: one file per method family over a shared base."""

import functools as _functools

from ._base import (
    AbstractLieSolver as AbstractLieSolver,
    ButcherTableau as ButcherTableau,
    CFTableau as CFTableau,
)
from ._cf import (
    CF4 as CF4,
    CF4_TABLEAU as CF4_TABLEAU,
    CG3 as CG3,
    CG3_TABLEAU as CG3_TABLEAU,
    LIE_EULER_TABLEAU as LIE_EULER_TABLEAU,
    CommutatorFree as CommutatorFree,
    LieEuler as LieEuler,
)
from ._diffrax import (
    TSIT5_TABLEAU as TSIT5_TABLEAU,
    DiffraxLieAdaptiveSolver as DiffraxLieAdaptiveSolver,
    DiffraxLieSolver as DiffraxLieSolver,
    LieInterpolation as LieInterpolation,
    LieTerm as LieTerm,
    RKMKTsit5 as RKMKTsit5,
    SceneVectorField as SceneVectorField,
    diffrax_solver as diffrax_solver,
    lie_term as lie_term,
)
from ._lgvi import LGVI as LGVI
from ._rkmk import (
    BS3_TABLEAU as BS3_TABLEAU,
    DOPRI5_TABLEAU as DOPRI5_TABLEAU,
    RK4_TABLEAU as RK4_TABLEAU,
    RKMK as RKMK,
    RKMK4 as RKMK4,
    RKMK32 as RKMK32,
    RKMK45 as RKMK45,
)

#: The fixed-step Lie-group methods by name (factories): what the command line accepts
#: as --method. The ``-cayley`` variants are RKMK in Cayley coordinates.
METHODS = {cls.__name__: cls for cls in (LieEuler, RKMK4, RKMK32, RKMK45, CG3, CF4, LGVI)}
METHODS.update(
    {f"{cls.__name__}-cayley": _functools.partial(cls, coords="cayley") for cls in (RKMK4, RKMK45)}
)


def method_by_name(text: str) -> str:
    """The canonical name in `METHODS` of ``text`` (case-insensitive), or ``ValueError``."""
    for name in METHODS:
        if name.lower() == text.lower():
            return name
    raise ValueError(f"unknown method {text!r} (choose from {', '.join(METHODS)})")
