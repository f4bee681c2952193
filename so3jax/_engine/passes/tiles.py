"""The ``"tiles"`` pass: a large batch of Jacobian programs run tile after tile on a CPU.

Program in, program out: `_in_tiles` runs a ``custom_vmap`` rule on ``n`` tiles of
``size`` runs under ``lax.map`` (sized by `batch_tiles`), so that a tile's values stay in
cache (docs/engine.md, "Tiles"). Each run's results are the untiled batch's:
``tests/passes/test_pass_tiles.py``. Speed: ``benchmarks/ablation.py`` (``large grad``),
``benchmarks/layouts.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

from ..policy import batched_layout, current, one_cpu_device


def batch_tiles(what: str, runs: int, columns: int = 0, observed: int = 1) -> tuple[int, int]:
    """``(n, size)``: ``runs`` runs of program ``what`` (``columns`` tangent columns,
    ``observed`` scalars per saved point) as ``n`` tiles of ``size``; ``(1, runs)``: untiled."""
    policy = current()
    values = policy.tile_values if what == "jacobian" else None
    if values is None or not policy.on("tiles") or not one_cpu_device():
        return 1, runs
    if observed > policy.tile_max_observed:
        return 1, runs
    scalar_from, _ = batched_layout(what)
    tile = 2 ** round(math.log2(values / (1 + columns)))
    n = round(runs / tile)
    if scalar_from is None or runs < scalar_from or n < 2:
        return 1, runs
    size = -(-runs // n)
    size = -(-size // policy.tile_multiple) * policy.tile_multiple
    if size < scalar_from:  # a tile runs the program a batch of its size would
        return 1, runs
    return -(-runs // size), size


def _in_tiles(rule: Callable, axis_size: int, n: int, size: int, in_batched, args):
    """``rule(axis_size, in_batched, *args)`` (a `custom_vmap` rule) as ``n`` tiles of
    ``size`` runs under `lax.map`; the padding runs (copies of the last) are dropped."""
    pad = n * size - axis_size
    leaves, treedef = jax.tree.flatten(args)
    flags = [bool(b) for b in jax.tree.leaves(in_batched)]

    def tiles(x):  # (B, ...) -> (n, size, ...)
        if pad:
            x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
        return x.reshape((n, size) + x.shape[1:])

    def one(tile):
        it = iter(tile)
        tile_args = jax.tree.unflatten(
            treedef, [next(it) if b else x for x, b in zip(leaves, flags, strict=True)]
        )
        return rule(size, in_batched, *tile_args)[0]

    outs = jax.lax.map(one, [tiles(x) for x, b in zip(leaves, flags, strict=True) if b])
    out = jax.tree.map(lambda y: y.reshape((n * size,) + y.shape[2:])[:axis_size], outs)
    return out, jax.tree.map(lambda _: True, out)
