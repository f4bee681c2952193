"""The engine's derivative programs of one loop, in the array layout.

`Programs` extends `so3jax._engine.loop.Loop` with the Jacobian program (`jac_array`; its
scalarized layout is `so3jax._engine.passes.scalarized`'s) and the discrete adjoint, from
residuals kept by the forward pass (`fwd_residuals`) or replayed from checkpointed segments
(`fwd_segments`). Each equals JAX's derivative of the reference to round-off
(``tests/test_engine.py``, ``tests/passes/``).

References: Griewank & Walther, *Evaluating Derivatives*, SIAM 2008, ch. 3 and 12.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from .loop import Loop
from .masks import _abstract_jaxpr, _mask_eval
from .passes.frames import (
    OBS_ZERO,
    _dense_mask,
    _frame_flags,
    _frame_step,
    _jvp_with_frames,
    _obs_kind,
    _obs_tangent,
)
from .trees import _fill, _floats, _pick, _with_floats


class Programs(Loop):
    """`Loop`'s reference programs and the derivative programs."""

    # ---------------- masked tangents ----------------
    # Only the float leaves flagged in ``mP``, ``mc`` (`_tangent_masks`) carry a tangent.

    @staticmethod
    def _masked(fn, mP, mc, P, c):
        """``(g, Pm, cm)``: ``fn(P, c)`` as ``g(Pm, cm)`` of the float leaves flagged in ``mP``,
        ``mc`` (the others held at ``P``, ``c``), and those leaves."""
        pf, cf = _floats(P), _floats(c)

        def g(Pm, cm):
            return fn(_with_floats(P, _fill(mP, Pm, pf)), _with_floats(c, _fill(mc, cm, cf)))

        return g, _pick(mP, pf), _pick(mc, cf)

    def _step_masked(self, mc, P, c, valid=None):
        """One step: ``(flagged float leaves, carry)``, or no step where ``valid`` is false (the
        padded tail of the last segment)."""
        c1 = self.step(P, c)
        if valid is not None:
            c1 = jax.tree.map(lambda a, b: jnp.where(valid, a, b), c1, c)
        return _pick(mc, _floats(c1)), c1

    def tangent_step(self, mP, mc, x):
        """One step of ``(P, c, dP, dc)``: the carry and one column of its tangent (the
        float leaves flagged in ``mc``; a `FRAME` leaf's as three numbers)."""
        P, c, dP, dc = x
        g, Pm, cm = self._masked(functools.partial(self._step_masked, mc), mP, mc, P, c)
        fr = _frame_flags(mc)
        if any(fr):
            dc1, c1 = _frame_step(g, Pm, cm, dP, dc, fr)
            return P, c1, dP, dc1
        _, dc1, c1 = jax.jvp(g, (Pm, cm), (list(dP), list(dc)), has_aux=True)
        return P, c1, dP, dc1

    def _obs_tangents(self, mP, mc, x) -> tuple[list, list]:
        """Flat lists of the observations and their tangents from `frame_jvp` (``None``, an
        array or a `Frame`)."""
        P, c, dP, dc = x
        o, Pm, cm = self._masked(self.observe, mP, mc, P, c)
        outs, touts, _ = _jvp_with_frames(o, Pm, cm, dP, dc, _frame_flags(mc))
        return outs, touts

    def obs_kinds(self, mP, mc, P, c0, elements: list) -> tuple:
        """Per observation leaf, its kind in the Jacobian programs (`OBS_ZERO`, ...), traced
        once, abstractly; `OBS_ZERO` too where no element depends on those flagged in
        ``elements`` (`_tangent_masks`), e.g. a reference attitude stacked with the body's."""
        pl, pt = jax.tree.flatten(P)
        cl, ct = jax.tree.flatten(c0)

        def obs(*leaves):
            P_, c_ = (
                jax.tree.unflatten(pt, leaves[: len(pl)]),
                jax.tree.unflatten(ct, leaves[len(pl) :]),
            )
            return jax.tree.leaves(self.observe(P_, c_))

        hit = [bool(m.any()) for m in _mask_eval(_abstract_jaxpr(obs, pl + cl), elements)]
        pf, cf = _floats(P), _floats(c0)
        fr = _frame_flags(mc)
        kinds = []

        def spec(x, frame=False):
            shape = jnp.shape(x)[:-2] + (3,) if frame else jnp.shape(x)
            return jax.ShapeDtypeStruct(shape, jnp.result_type(x))

        def probe(dP, dc):
            outs, touts = self._obs_tangents(mP, mc, (P, c0, dP, dc))
            kinds[:] = [_obs_kind(o, t) for o, t in zip(outs, touts, strict=True)]
            return 0

        dP = [spec(x) for x in _pick(mP, pf)]
        dc = [spec(x, f) for x, f in zip(_pick(mc, cf), fr, strict=True)]
        jax.make_jaxpr(probe)(dP, dc)
        return tuple(k if h else OBS_ZERO for k, h in zip(kinds, hit, strict=True))

    def observation_tangents(self, mP, mc, mo, x) -> list:
        """The Jacobian programs' observation tangents of one column: the leaves whose
        kind in ``mo`` is not `OBS_ZERO`, each as its kind stores it (`_obs_tangent`)."""
        outs, touts = self._obs_tangents(mP, mc, x)
        return [
            _obs_tangent(o, t, k) for o, t, k in zip(outs, touts, mo, strict=True) if k != OBS_ZERO
        ]

    # ---------------- Jacobian (a few inputs) ----------------

    def jac_array(self, mP, mc, mo, P, c0, dP, dc0):
        """The run and its Jacobian's columns in one pass, array layout.

        ``dP``, ``dc0``: masked tangents with a leading axis of ``n`` columns, batched over
        one primal. Returns ``(ys, cN, dys, dcN)``, the column axis after the saved-point
        axis of ``dys`` and first in ``dcN``; ``dys`` lists the observations whose kind in
        ``mo`` (`obs_kinds`) is not `OBS_ZERO`. Rotations' tangents are nine numbers here.
        """
        mc = _dense_mask(mc)
        tobs = functools.partial(self.observation_tangents, mP, mc, mo)

        def observe(x):
            P, c, dP, dc = x
            cols = jax.vmap(lambda dP, dc: tobs((P, c, dP, dc)))
            return self.observe(P, c), cols(dP, dc)

        body = functools.partial(self._jac_body, mP, mc)
        x, (ys, dys) = self.save_loop(body, observe, (P, c0, dP, dc0))
        return ys, x[1], dys, x[3]

    def _jac_body(self, mP, mc, x):
        """One step of `jac_array`: ``(P, c, dP, dc)`` -> the same after the step."""
        P, c, dP, dc = x
        tstep = functools.partial(self.tangent_step, mP, mc)
        cols = jax.vmap(lambda dP, dc: tstep((P, c, dP, dc)), out_axes=(None, None, 0, 0))
        return cols(dP, dc)

    def jac_step(self, mP, mc, Pj, cj):
        """`_jac_body` as a step of a loop with parameters ``(P, dP)`` and carry
        ``(c, dc)`` (`so3jax._engine.passes.settle.jacobian_tangents`)."""
        (P, dP), (c, dc) = Pj, cj
        _, c1, _, dc1 = self._jac_body(mP, _dense_mask(mc), (P, c, dP, dc))
        return c1, dc1

    # ---------------- adjoint (docs/engine.md, "Through more scalars") ----------------
    # Only the leaves flagged in ``mP``, ``mc`` are differentiated; the others' gradients are 0.

    def _replay(self, mP, mc, layout: list, P, c0, first, n_blocks: int, observe=True):
        """``(cN, (ys, res, cs))``: ``n_blocks`` save blocks from ``c0`` (indices from ``first``;
        those past `n_save` leave the carry alone); per step the residuals of JAX's ``vjp`` of
        the step, packed (`_packed_vjp`; ``layout`` gets the packing), ``(n_blocks, save_every,
        ...)``; per block the observations (with ``observe``) and the carry after it."""
        padded = self.n_save % n_blocks != 0

        def one(j, c, _):
            valid = j < self.n_save if padded else None
            step = functools.partial(self._step_masked, mc, valid=valid)
            g, Pm, cm = self._masked(step, mP, mc, P, c)
            return _packed_vjp(layout, g, Pm, cm)

        def block(c, j):
            if self.save_every == 1:
                c1, res = one(j, c, None)
                res = jax.tree.map(lambda a: a[None], res)
            else:
                c1, res = jax.lax.scan(functools.partial(one, j), c, None, length=self.save_every)
            return c1, (self.observe(P, c1) if observe else None, res, c1)

        return jax.lax.scan(block, c0, first + jnp.arange(n_blocks))

    def _backward(self, mP, mc, keep, layout: list, P, res, cs, ct_obs, carry):
        """``(lam, acc)``, the cotangents of the carry's and the parameters' flagged leaves, after
        `_replay`'s blocks pulled back, last first, from ``carry`` and ``ct_obs`` (per block,
        for the observations flagged in ``keep``)."""

        def observed(P, c):
            return _pick(keep, jax.tree.leaves(self.observe(P, c)))

        def step_back(carry, packed):
            lam, acc = carry
            gP, lam = _packed_pullback(layout, packed)(lam)
            return (lam, [a + g for a, g in zip(acc, gP, strict=True)]), None

        def block(carry, x):
            (lam, acc), (res, c, ct) = carry, x
            if ct:
                g, Pm, cm = self._masked(observed, mP, mc, P, c)
                gP, gc = jax.vjp(g, Pm, cm)[1](ct)
                lam = [a + g for a, g in zip(lam, gc, strict=True)]
                acc = [a + g for a, g in zip(acc, gP, strict=True)]
            if self.save_every == 1:
                return step_back((lam, acc), jax.tree.map(lambda a: a[0], res))
            return jax.lax.scan(step_back, (lam, acc), res, reverse=True)

        return jax.lax.scan(block, carry, (res, cs, list(ct_obs)), reverse=True)[0]

    def _gradients(self, mP, mc, P, ct_cN, backward):
        """``(gP, gc0)`` from ``backward((lam, acc)) -> (lam, acc)`` started at the final
        carry's cotangents ``ct_cN`` (one per float leaf of the carry)."""
        pf = _floats(P)
        lam, acc = backward((_pick(mc, ct_cN), [jnp.zeros_like(p) for p in _pick(mP, pf)]))
        gP = _fill(mP, acc, [jnp.zeros_like(p) for p in pf])
        return gP, _fill(mc, lam, [jnp.zeros_like(c) for c in ct_cN])

    def fwd_residuals(self, mP, mc, layout: list, P, c0):
        """``((ys, cN), (res, cs))``: `fwd_array`'s run with every step's residuals and the
        carry at every saved point (`_replay`). Memory linear in ``n_steps`` (bounded by the
        policy's ``adjoint_residual_bytes``)."""
        cN, (ys, res, cs) = self._replay(mP, mc, layout, P, c0, 0, self.n_save)
        return (ys, cN), (res, cs)

    def adj_residuals(self, mP, mc, keep, layout: list, P, saved, ct_obs, ct_cN):
        """The discrete adjoint from `fwd_residuals`' ``saved``: ``(gP, gc0)`` for the float
        leaves of ``P``, ``c0``, given ``ct_obs`` (per saved point, for the observations flagged
        in ``keep``) and ``ct_cN`` (per float leaf of the final carry). Nothing replayed."""
        res, cs = saved
        back = functools.partial(self._backward, mP, mc, keep, layout, P, res, cs, ct_obs)
        return self._gradients(mP, mc, P, ct_cN, back)

    def fwd_segments(self, P, c0):
        """``((ys, cN), ck)``: `fwd_array`'s run and the carries at the starts of its
        checkpointed segments (`blocks_per_segment` save blocks each), in one pass."""
        ys, cN, ck = self._in_segments(P, c0, self.blocks_per_segment, starts=True)
        return (ys, cN), ck

    def adj_segments(self, mP, mc, keep, P, c0, ct_obs, ct_cN, ck=None):
        """The discrete adjoint from `fwd_segments`' carries ``ck`` (``None``: one segment),
        as `adj_residuals`; each segment replayed from its start, last first. Memory
        ``~ K + n / K`` steps."""
        m, S = self.blocks_per_segment, self.segments

        def per_segment(a):  # (n_save, ...) -> (S, m, ...), the padded tail zero
            a = jnp.concatenate([a, jnp.zeros((S * m - self.n_save,) + a.shape[1:], a.dtype)])
            return a.reshape((S, m) + a.shape[1:])

        def segment(carry, x):
            s, c, cts = x
            layout: list = []
            _, (_, res, cs) = self._replay(mP, mc, layout, P, c, s * m, m, observe=False)
            return self._backward(mP, mc, keep, layout, P, res, cs, cts, carry), None

        cts = [per_segment(a) for a in ct_obs]

        def backward(carry):
            if S == 1:  # no scan: XLA's older CPU emitter aborts on it hoisted whole
                return segment(carry, (0, c0, [a[0] for a in cts]))[0]
            return jax.lax.scan(segment, carry, (jnp.arange(S), ck, cts), reverse=True)[0]

        return self._gradients(mP, mc, P, ct_cN, backward)


def _packed_vjp(layout: list, g, *primals):
    """``(aux, packed)``: JAX's ``vjp`` of ``g`` (``-> (out, aux)``) at ``primals``, with its
    pullback's residuals packed (`_pack`); ``layout`` receives their tree and packing."""
    _, pull, aux = jax.vjp(g, *primals, has_aux=True)
    leaves, tree = jax.tree.flatten(pull)
    packed, spec = _pack(leaves)
    layout[:] = [tree, spec]
    return aux, packed


def _packed_pullback(layout: list, packed):
    """The pullback whose residuals `_packed_vjp` packed into ``packed``."""
    tree, spec = layout
    return jax.tree.unflatten(tree, _unpack(packed, spec))


def _pack(leaves: list) -> tuple[list, list]:
    """``(packed, spec)``: ``leaves`` raveled into one vector per dtype, and how to undo it
    (`_unpack`): XLA compiles a kernel per array a loop stacks and per read of it."""
    groups: dict = {}  # dtype -> raveled leaves, in order
    spec = []  # per leaf: (its dtype's index in ``groups``, its shape)
    for x in leaves:
        x = jnp.asarray(x)
        group = groups.setdefault(x.dtype, [])
        spec.append((list(groups).index(x.dtype), x.shape))
        group.append(jnp.ravel(x))
    return [jnp.concatenate(g) if len(g) > 1 else g[0] for g in groups.values()], spec


def _unpack(packed: list, spec: list) -> list:
    """The leaves `_pack` packed into ``packed`` with ``spec``."""
    starts: dict = {}
    out = []
    for g, shape in spec:
        at = starts.get(g, 0)
        size = math.prod(shape)
        out.append(packed[g][at : at + size].reshape(shape))
        starts[g] = at + size
    return out
