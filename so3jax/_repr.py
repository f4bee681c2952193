"""Readable reprs of modules whose leaves are small concrete arrays (gains, bodies, scenes).

Equinox prints an array leaf by its dtype and shape (``k_R=f64[]``), which hides
the numbers a reader wants from a gain or an inertia. `module_repr` prints
small concrete leaves by value instead, in a compact NumPy-like form
(``GeometricGains(k_R=8.81, k_Omega=2.54)``, ``k_R=[8.81, 8.81, 8.81]``), and
keeps equinox's form for every other leaf: arrays of more than `MAX_SHOWN`
entries, tracers (a repr under `jax.jit` or `jax.vmap`), and arrays that live
partly on other processes.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

#: Arrays with at most this many entries are printed by value (a 3x3 inertia is).
MAX_SHOWN = 9
#: Significant digits of a printed entry.
DIGITS = 6


class _Shown:
    """A leaf stand-in whose repr is the given text (read by `eqx.tree_pformat`)."""

    __slots__ = ("text",)

    def __init__(self, text: str):
        self.text = text

    def __repr__(self) -> str:
        return self.text


def _number(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, complex | np.complexfloating):
        return f"{complex(v):.{DIGITS}g}"
    text = f"{float(v):.{DIGITS}g}"
    # "1.0", not "1": a float reads as one (nan, inf and 1e-07 already do)
    return text if any(c in text for c in ".eni") else text + ".0"


def format_values(a) -> str:
    """One line for a small array: ``8.81`` for a scalar, ``[1, 2, 3]`` for a vector.

    **Arguments:**

    - `a`: an array (NumPy or concrete JAX).

    **Returns:** the entries with `DIGITS` significant digits, nested like lists.
    """
    a = np.asarray(a)
    if a.ndim == 0:
        return _number(a.item())
    return "[" + ", ".join(format_values(b) for b in a) + "]"


def _shown(x):
    if isinstance(x, jax.core.Tracer):
        return x
    if isinstance(x, jax.Array):
        if x.size > MAX_SHOWN or not x.is_fully_addressable:
            return x
        return _Shown(format_values(x))
    if isinstance(x, np.ndarray | np.generic) and np.size(x) <= MAX_SHOWN:
        return _Shown(format_values(x))
    return x


def module_repr(self) -> str:
    """The equinox repr of ``self`` with small concrete array leaves printed by value.

    Attach it to a module class as ``__repr__ = module_repr``. Nested modules
    are printed the same way; tracers and arrays of more than `MAX_SHOWN`
    entries keep equinox's ``f64[3,3]`` form.

    **Arguments:**

    - `self`: an `equinox.Module`.

    **Returns:** the text.
    """
    try:
        shown = jax.tree_util.tree_map(_shown, self)
    except Exception:  # an unusual pytree: equinox's own form is always safe
        return eqx.tree_pformat(self)
    return eqx.tree_pformat(shown)
