"""Log-scale panels with a floor at the resolution of the data's floating-point type.

A log axis cannot show zero, and below the round-off of the numbers it plots a
curve shows only noise. Every log panel of `so3jax.plot` therefore draws
``max(y, floor)`` and keeps its lower limit at or above ``floor``, where

    floor = eps(dtype) * scale

with ``eps`` the machine epsilon of the data's type (`numpy.finfo`) and
``scale`` the size of the quantity's round-off in units of ``eps``. A quantity
computed with a relative error of ``eps`` uses its largest value over the run
(`peak`): ``|e_Omega|`` starting at exactly 0 is drawn from ``eps |Omega|_max``,
not from ``1e-300``. ``Psi`` from the trace formula (absolute round-off ``eps``)
uses ``scale = 1``, so a value of ``-1.8e-15`` shows as the floor; ``Psi`` from
``atan2`` (`plot.error_function`) resolves angles down to ``eps`` and so uses
``scale = eps`` (``Psi ~ angle^2 / 2``). Panels that draw machine epsilon as a
reference line use ``scale = 1/100``, so round-off shows above the floor.

The axis keeps autoscaling as lines are added; whenever its y limits change, a
lower limit below the floor is lifted to it (also when every value sits at the
floor, where matplotlib would widen the range by a decade). With several floors
on one axis the lowest one holds.
"""

from __future__ import annotations

import numpy as np


def resolution(dtype) -> float:
    """Machine epsilon of ``dtype`` (float64's for a non-floating type)."""
    dt = np.dtype(dtype)
    return float(np.finfo(dt if np.issubdtype(dt, np.floating) else np.float64).eps)


def peak(*series) -> float:
    """Largest finite absolute value over the given arrays (1 if none is positive)."""
    best = 0.0
    for y in series:
        a = np.abs(np.asarray(y, dtype=np.float64))
        a = a[np.isfinite(a)]
        if a.size:
            best = max(best, float(a.max()))
    return best if best > 0 else 1.0


def log_floor(dtype, scale: float = 1.0) -> float:
    """The lowest value a log panel of data in ``dtype`` shows: ``eps(dtype) * scale``.

    **Arguments:**

    - `dtype`: the floating-point type the plotted data were computed in.
    - `scale`: the quantity's round-off in units of ``eps`` (its `peak` for a
      relative error of ``eps``); a non-positive or non-finite scale counts as 1.

    **Returns:** the floor, a positive float.
    """
    scale = float(scale)
    if not (np.isfinite(scale) and scale > 0):
        scale = 1.0
    return resolution(dtype) * scale


def log_line(ax, x, y, *args, floor: float, **kwargs):
    """``ax.semilogy(x, max(y, floor))`` that keeps the axis's lower limit at ``floor`` or above.

    NaN stays NaN (a gap); negative values (round-off of a quantity that is
    ``>= 0``) and zeros are drawn at the floor.

    **Arguments:**

    - `ax`: a matplotlib ``Axes``.
    - `x`, `y`: the data, shape `(n,)`.
    - `*args`, `**kwargs`: passed to ``semilogy`` (a format string, a label, ...).
    - `floor`: the floor, from `log_floor`.

    **Returns:** the ``Line2D``.
    """
    y = np.asarray(y, dtype=np.float64)
    shown = np.where(np.isnan(y), np.nan, np.maximum(y, floor))
    (line,) = ax.semilogy(x, shown, *args, **kwargs)
    hold_floor(ax, floor)
    return line


#: Attribute of an ``Axes`` holding its floor (set by `hold_floor`).
_FLOOR = "_so3jax_log_floor"


def hold_floor(ax, floor: float) -> float:
    """Keep the lower y limit of ``ax`` at or above ``floor`` (the lowest floor given).

    **Arguments:**

    - `ax`: a matplotlib ``Axes`` with a log y axis.
    - `floor`: a floor to add to those already held, > 0.

    **Returns:** the floor now held (the lowest).
    """
    held = getattr(ax, _FLOOR, None)
    setattr(ax, _FLOOR, floor if held is None else min(floor, held))
    if held is None:
        ax.callbacks.connect("ylim_changed", _lift)
    _lift(ax)
    return getattr(ax, _FLOOR)


def _lift(ax) -> None:
    """Raise a lower y limit below the axis's floor to it (a ``ylim_changed`` callback)."""
    floor = getattr(ax, _FLOOR)
    lo, hi = ax.get_ylim()
    if lo < floor:
        # auto=None: autoscaling stays on; the call's own ylim_changed finds lo == floor.
        ax.set_ylim(floor, max(hi, 10.0 * floor), auto=None)
