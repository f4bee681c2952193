"""The reference programs: a plain ``lax.scan`` and its checkpointed segments.

For reverse mode, segments of about ``sqrt(n_steps)`` steps under `jax.checkpoint` (Griewank
& Walther, *Evaluating Derivatives*, SIAM 2008, ch. 12). Never re-interpreted: with every pass
off and ``program="autodiff"``, a run is `Loop.fwd_checkpointed`, differentiated and batched
by JAX alone.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from .policy import current


def _segment_blocks(n: int, target: int) -> int:
    """Blocks per segment: a divisor of ``n`` within 2x of ``target`` (no padded tail, whose
    masks cost a select per carry leaf and step) if there is one, else ``target``."""
    target = max(1, min(n, target))
    for d in sorted(
        range(max(1, target // 2), min(n, 2 * target) + 1), key=lambda d: abs(d - target)
    ):
        if n % d == 0:
            return d
    return target


def checkpoint_length(n_steps: int) -> int:
    """Steps per checkpointed segment: about ``sqrt(n_steps)``."""
    return max(1, math.ceil(math.sqrt(n_steps)))


class Loop:
    """The reference programs of one fixed-step loop: ``lax.scan`` of the step as written.

    ``step(P, c) -> c`` and ``observe(P, c) -> pytree`` are pure. Every other program of the
    engine (`so3jax._engine.programs.Programs`) equals `fwd_array` to round-off.
    """

    def __init__(self, step, observe, n_steps: int, save_every: int, K: int):
        self.step, self.observe = step, observe
        self.n, self.save_every, self.n_save = n_steps, save_every, n_steps // save_every
        self.K = min(K, n_steps)
        self.jaxprs: dict = {}  # the step's, by argument shapes (`_tangent_masks`' cache)

    @property
    def blocks_per_segment(self) -> int:
        """Save blocks per checkpointed segment: about ``K`` steps (`_segment_blocks`)."""
        return _segment_blocks(self.n_save, max(1, round(self.K / self.save_every)))

    @property
    def segments(self) -> int:
        """Checkpointed segments: the last one padded with blocks that leave the carry alone."""
        return -(-self.n_save // self.blocks_per_segment)

    def _repeat(self, fn, x):
        """``save_every`` applications of ``fn`` under ``lax.scan``."""
        return jax.lax.scan(
            lambda x, _: (fn(x), None),
            x,
            None,
            length=self.save_every,
            unroll=current().scan_unroll,
        )[0]

    def save_loop(self, body, observe, x0):
        """``n_save`` blocks of ``save_every`` applications of ``body``, observed after each."""

        def block(x, _):
            x = body(x) if self.save_every == 1 else self._repeat(body, x)
            return x, observe(x)

        unroll = current().scan_unroll if self.save_every == 1 else 1
        return jax.lax.scan(block, x0, None, length=self.n_save, unroll=unroll)

    def fwd_array(self, P, c0):
        cN, ys = self.save_loop(lambda c: self.step(P, c), lambda c: self.observe(P, c), c0)
        return ys, cN

    def fwd_checkpointed(self, P, c0):
        """The array program with checkpointed segments: what plain autodiff differentiates.

        Segments of about ``K`` steps: reverse mode stores one carry per segment and
        recomputes its residuals, memory ``~ n / K + K`` steps instead of ``n``.
        """
        ys, cN, _ = self._in_segments(P, c0, self.blocks_per_segment, checkpoint=True)
        return ys, cN

    def _in_segments(self, P, c0, m: int, checkpoint: bool = False, starts: bool = False):
        """``(ys, cN, ck)``: `fwd_array`'s run as ``ceil(n_save / m)`` segments of ``m`` save
        blocks (under `jax.checkpoint` with ``checkpoint``; the last padded); ``ck``: the
        carry at each segment's start with ``starts``, else ``None``."""
        step, obs = self.step, self.observe
        S = -(-self.n_save // m)
        padded = S * m != self.n_save

        def block(c, i):
            c1 = step(P, c) if self.save_every == 1 else self._repeat(lambda c: step(P, c), c)
            o = obs(P, c1)
            if padded:
                c1 = jax.tree.map(lambda a, b: jnp.where(i < self.n_save, a, b), c1, c)
            return c1, o

        def segment(c, s):
            c1, ys = jax.lax.scan(block, c, s * m + jnp.arange(m))
            return c1, ((c, ys) if starts else ys)

        if checkpoint:
            segment = jax.checkpoint(segment, prevent_cse=False)
        cN, out = jax.lax.scan(segment, c0, jnp.arange(S))
        ck, ys = out if starts else (None, out)
        ys = jax.tree.map(lambda a: a.reshape((S * m,) + a.shape[2:])[: self.n_save], ys)
        return ys, cN, ck
