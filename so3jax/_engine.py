"""The execution engine: how every fixed-step run executes.

`simulate`, `rollout_cost` / `expected_cost`, `sweep` and `tune` all step a
carry with a pure step function and save observations every ``save_every``
steps. They hand that loop to `run`, which picks the program for what the call
is, with no flag for the user to know:

- **a single run** executes the array program: ``lax.scan`` over the step as
  written (3-vectors and 3x3 matrices), the fastest layout for one trajectory;
- **a batch under ``vmap``** executes the scalarized program
  (`so3jax._scalarize`): every scalar component of the carry is its own
  contiguous ``(B,)`` array and a step is a few hundred small elementwise
  kernels (a structure-of-arrays layout). The switch is a
  `jax.custom_batching.custom_vmap` rule, so nested ``vmap`` (gains x
  attitudes) and ``vmap`` inside ``jit`` take it. On CPU the rule also hands
  the program an unbatched index (`so3jax._scalarize.cut_index`) with which it
  cuts fusion where XLA would recompute shared values once per consumer
  (`so3jax._scalarize.fusion_cut`);
- **a differentiated run** hangs its derivatives on one ``jax.custom_jvp``
  whose tangent is a `jax.custom_derivatives.linear_call`. Forward mode
  (``jvp``, ``jacfwd``) runs the engine's tangent program, a scan of
  ``jax.jvp`` of one step, scalarized for batches of 32 runs or more. Reverse
  mode (``grad``) through at most `FORWARD_JACOBIAN_MAX` differentiated
  scalars (two gains, six per-axis gains) takes the Jacobian's columns from
  that tangent program, one run each, and contracts them with the
  cotangents: its memory does not grow with the horizon beyond the saved
  points. Through more scalars it is JAX's transpose of the *checkpointed*
  array program (segments of about ``sqrt(n_steps)`` steps under
  `jax.checkpoint`), whose memory grows like ``sqrt(n_steps)``. The value of a
  differentiated batch still comes from the scalarized program.
  ``program="autodiff"`` is JAX's own derivative of the checkpointed array
  program throughout (the reference).

``program="adjoint"`` keeps the tangent program and makes reverse mode a
**discrete adjoint** whatever the number of inputs (a backward scan of ``jax.vjp`` of
one step and its observation, with the states recomputed from checkpoints every
``K ~ sqrt(n_steps)`` steps), exact to round-off against plain autodiff. JAX ships
no batching rule for ``linear_call``; `_register_linear_call_batching` adds one,
so ``vmap(grad(...))`` and ``jacfwd`` work through it. Both derivative programs
exist in the scalarized layout too (`BATCHED_LAYOUT`). The tangent program takes
it for batches of 32 runs or more, where (with fusion cuts) ``jacfwd`` of the mean
cost over 256 seed starts ran about 5x faster than JAX's ``jvp`` of the array
program. The adjoint stays in the array layout:
XLA on CPU takes minutes to compile the scalarized one (the scalarized adjoint
step of the seed has about 9400 scalar operations: 24 s to compile unbatched,
100 s under ``vmap``, against about 3 s for the forward step). See
``benchmarks/README.md`` for the measured ratios.

Every program exists in both layouts (array and scalarized); a step with a
primitive the scalarizer does not handle (a loop, dynamic indexing) runs the
array program in every case, with a warning.

References: A. Griewank, A. Walther, *Evaluating Derivatives*, SIAM 2008
(discrete adjoints, ch. 3; checkpointing, ch. 12); JAX's ``linear_call``
docstring (a linear function with a custom transpose).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap
from jax.custom_derivatives import SymbolicZero, linear_call

from . import _scalarize as sc

__all__ = ["run", "checkpoint_length"]


# --------------------------------------------------------------------------
# pytrees split into float leaves (differentiable) and the rest
# --------------------------------------------------------------------------


def _is_float(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def _floats(tree) -> list:
    return [x for x in jax.tree.leaves(tree) if _is_float(x)]


def _with_floats(tree, floats):
    leaves, treedef = jax.tree.flatten(tree)
    it = iter(floats)
    new = [next(it) if _is_float(x) else x for x in leaves]
    return jax.tree.unflatten(treedef, new)


def _tangent_tree(primal, float_tangents):
    """A tangent pytree for ``primal``: the given float tangents, float0 zeros elsewhere."""
    leaves, treedef = jax.tree.flatten(primal)
    it = iter(float_tangents)
    new = [next(it) if _is_float(x) else np.zeros(jnp.shape(x), jax.dtypes.float0) for x in leaves]
    return jax.tree.unflatten(treedef, new)


def _fill(nz: list, xs, others: list) -> list:
    """``others`` with the entries flagged in ``nz`` replaced, in order, by ``xs``."""
    it = iter(xs)
    return [next(it) if z else o for z, o in zip(nz, others, strict=True)]


def _segment_blocks(n: int, target: int) -> int:
    """Blocks per segment: a divisor of ``n`` within 2x of ``target`` if there is one.

    A divisor needs no padded tail (whose masks cost a select per carry leaf
    and step); otherwise ``target`` itself, and the last segment is padded.
    """
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


# --------------------------------------------------------------------------
# array / scalarized programs behind one custom_vmap
# --------------------------------------------------------------------------


#: The layout each program takes when batched (see `_dual`): ``"auto"`` is the
#: scalarized layout for batches of `so3jax._scalarize.CUT_MIN_BATCH` runs or more
#: (fusion cuts on), the array layout below that.
BATCHED_LAYOUT = {"run": "scalar", "tangent": "auto", "adjoint": "array"}


def _dual(array_fn: Callable, scalar_fn: Callable, what: str) -> Callable:
    """``array_fn`` when unbatched; ``vmap`` of ``scalar_fn`` when batched.

    ``scalar_fn`` raises `ScalarizeError` at trace time for an unsupported
    primitive (a loop, dynamic indexing, `jax.checkpoint` inside the step); the
    batched call then vmaps ``array_fn``, silently: nobody asked for the
    scalarized program.
    """
    fn = custom_vmap(array_fn)

    @fn.def_vmap
    def _rule(axis_size, in_batched, *args):
        axes = tuple(jax.tree.map(lambda b: 0 if b else None, ib) for ib in in_batched)
        large = axis_size >= sc.CUT_MIN_BATCH  # fusion cuts pay from here on
        layout = BATCHED_LAYOUT[what]
        if layout == "auto":
            layout = "scalar" if large else "array"
        if layout == "array":
            out = jax.vmap(array_fn, in_axes=axes)(*args)
            return out, jax.tree.map(lambda _: True, out)
        try:
            index = sc.cut_index(args) if large else None
            cut = functools.partial(scalar_fn, cut=index)
            out = jax.vmap(cut, in_axes=axes)(*args)
        except sc.ScalarizeError:
            out = jax.vmap(array_fn, in_axes=axes)(*args)
        return out, jax.tree.map(lambda _: True, out)

    return fn


class _Loop:
    """The programs of one fixed-step loop (forward, tangent, adjoint), both layouts."""

    def __init__(self, step, observe, n_steps: int, save_every: int, K: int):
        self.step, self.observe = step, observe
        self.n, self.save_every, self.n_save = n_steps, save_every, n_steps // save_every
        self.K = min(K, n_steps)
        self.S = -(-n_steps // self.K)

    def _repeat(self, fn, x):
        """``save_every`` applications of ``fn`` under ``lax.scan``."""
        return jax.lax.scan(lambda x, _: (fn(x), None), x, None, length=self.save_every)[0]

    def _save_loop(self, body, observe, x0):
        """``n_save`` blocks of ``save_every`` applications of ``body``, observed after each."""

        def block(x, _):
            x = body(x) if self.save_every == 1 else self._repeat(body, x)
            return x, observe(x)

        return jax.lax.scan(block, x0, None, length=self.n_save)

    # ---------------- forward ----------------

    def fwd_array(self, P, c0):
        cN, ys = self._save_loop(lambda c: self.step(P, c), lambda c: self.observe(P, c), c0)
        return ys, cN

    def fwd_checkpointed(self, P, c0):
        """The array program with checkpointed segments: what plain autodiff differentiates.

        Save blocks are grouped into segments of about ``K`` steps, each under
        `jax.checkpoint`, so reverse mode stores one carry per segment and
        recomputes a segment's residuals when it transposes it: memory
        ``~ n / K + K`` steps instead of ``n``. The last segment is padded
        with blocks that leave the carry alone.
        """
        step, obs = self.step, self.observe
        m = _segment_blocks(self.n_save, max(1, round(self.K / self.save_every)))
        S = -(-self.n_save // m)
        padded = S * m != self.n_save

        def block(c, i):
            c1 = step(P, c) if self.save_every == 1 else self._repeat(lambda c: step(P, c), c)
            o = obs(P, c1)
            if padded:
                c1 = jax.tree.map(lambda a, b: jnp.where(i < self.n_save, a, b), c1, c)
            return c1, o

        @functools.partial(jax.checkpoint, prevent_cse=False)
        def segment(c, s):
            return jax.lax.scan(block, c, s * m + jnp.arange(m))

        cN, ys = jax.lax.scan(segment, c0, jnp.arange(S))
        ys = jax.tree.map(lambda a: a.reshape((S * m,) + a.shape[2:])[: self.n_save], ys)
        return ys, cN

    def fwd_scalar(self, P, c0, cut=None):
        ex = (P, c0)
        body, _ = sc.flat_program(lambda pc: (pc[0], self.step(*pc)), ex, cut)
        obs, obs_struct = sc.flat_program(lambda pc: self.observe(*pc), ex, cut)
        flat, ys = self._save_loop(body, obs, sc.split(ex))
        _, cN = sc.join(flat, jax.eval_shape(lambda: ex))
        return sc.join(ys, obs_struct, (self.n_save,)), cN

    # ---------------- tangent (forward mode) ----------------

    def _tstep(self, x):
        P, c, dP, dc = x

        def g(Pf, cf):
            c1 = self.step(_with_floats(P, Pf), _with_floats(c, cf))
            return _floats(c1), c1

        _, dc1, c1 = jax.jvp(g, (_floats(P), _floats(c)), (dP, dc), has_aux=True)
        return P, c1, dP, dc1

    def _tobs(self, x):
        P, c, dP, dc = x
        o = lambda Pf, cf: self.observe(_with_floats(P, Pf), _with_floats(c, cf))
        return jax.jvp(o, (_floats(P), _floats(c)), (dP, dc))[1]

    def tan_array(self, P, c0, dP, dc0):
        x, dys = self._save_loop(self._tstep, self._tobs, (P, c0, dP, dc0))
        return dys, x[3]

    def tan_scalar(self, P, c0, dP, dc0, cut=None):
        ex = (P, c0, dP, dc0)
        body, _ = sc.flat_program(self._tstep, ex, cut)
        tobs, tobs_struct = sc.flat_program(self._tobs, ex, cut)
        flat, dys = self._save_loop(body, tobs, sc.split(ex))
        x = sc.join(flat, jax.eval_shape(lambda: ex))
        return sc.join(dys, tobs_struct, (self.n_save,)), x[3]

    # ---------------- adjoint (reverse mode) ----------------

    def _masked_step(self, P, c, j):
        """One step, or nothing past the end (the last segment is padded)."""
        c1 = self.step(P, c)
        return jax.tree.map(lambda a, b: jnp.where(j < self.n, a, b), c1, c)

    def _vjp_step(self, x):
        """Cotangents through step ``j`` and the observation after it, accumulated.

        ``x = (P, c_j, lam, acc, ct_obs, is_save, valid)``: ``lam`` is the
        cotangent of the state after step ``j`` (from later steps), ``ct_obs``
        the cotangent of the observation of that state (used where ``is_save``).
        Returns the cotangent of ``c_j`` and ``acc`` plus the parameters' share.
        """
        P, c, lam, acc, ct_o, is_save, valid = x

        def h(Pf, cf):
            Pp = _with_floats(P, Pf)
            c1 = self.step(Pp, _with_floats(c, cf))
            return _floats(c1), self.observe(Pp, c1)

        _, pull = jax.vjp(h, _floats(P), _floats(c))
        ct_o = jax.tree.map(lambda a: a * is_save.astype(a.dtype), ct_o)
        gP, gc = pull((lam, ct_o))
        lam = [jnp.where(valid, g, l) for g, l in zip(gc, lam, strict=True)]
        acc = [a + jnp.where(valid, g, jnp.zeros_like(g)) for a, g in zip(acc, gP, strict=True)]
        return lam, acc

    def _segment_cts(self, ct_obs, s):
        """Observation cotangents for the steps of segment ``s`` (zero off save points)."""
        j = s * self.K + jnp.arange(self.K)
        m = (j + 1) // self.save_every - 1
        is_save = ((j + 1) % self.save_every == 0) & (j < self.n)
        m = jnp.clip(m, 0, self.n_save - 1)
        return j, jax.tree.map(lambda a: a[m], ct_obs), is_save

    def adj_array(self, P, c0, ct_obs, ct_cN):
        K, S = self.K, self.S

        def advance(c, s):  # one segment, saving nothing
            def one(c, i):
                return self._masked_step(P, c, s * K + i), None

            return jax.lax.scan(one, c, jnp.arange(K))[0], c

        _, ckpts = jax.lax.scan(advance, c0, jnp.arange(S))

        def segment(carry, s_ck):
            lam, acc = carry
            s, ck = s_ck

            def one(c, i):
                return self._masked_step(P, c, s * K + i), c

            _, states = jax.lax.scan(one, ck, jnp.arange(K))
            j, cts, is_save = self._segment_cts(ct_obs, s)

            def back(carry, x):
                lam, acc = carry
                c, ct_o, sv, jj = x
                return self._vjp_step((P, c, lam, acc, ct_o, sv, jj < self.n)), None

            (lam, acc), _ = jax.lax.scan(back, (lam, acc), (states, cts, is_save, j), reverse=True)
            return (lam, acc), None

        acc0 = [jnp.zeros_like(p) for p in _floats(P)]
        (lam, acc), _ = jax.lax.scan(
            segment, (list(ct_cN), acc0), (jnp.arange(S), ckpts), reverse=True
        )
        return acc, lam

    def adj_scalar(self, P, c0, ct_obs, ct_cN, cut=None):
        K, S = self.K, self.S
        j0 = jnp.zeros((), jnp.int32)
        ex_step = (P, c0, j0)
        mstep, _ = sc.flat_program(lambda x: (x[0], self._masked_step(*x), x[2] + 1), ex_step, cut)
        nP = len(sc.split(P))
        nc = len(sc.split(c0))

        def advance_flat(fc, s, keep):
            """K masked steps from the flat state ``fc``; the states before each if ``keep``."""
            flat = sc.split(P) + fc + [jnp.asarray(s * K, jnp.int32)]

            def one(f, _):
                return mstep(f), (f[nP : nP + nc] if keep else None)

            f, ys = jax.lax.scan(one, flat, None, length=K)
            return f[nP : nP + nc], ys

        def ckpt(fc, s):
            return advance_flat(fc, s, False)[0], fc

        _, ck_flat = jax.lax.scan(ckpt, sc.split(c0), jnp.arange(S))

        lam0 = list(ct_cN)
        acc0 = [jnp.zeros_like(p) for p in _floats(P)]
        ct_o_ex = jax.tree.map(lambda a: a[0], ct_obs)
        ex_back = (P, c0, lam0, acc0, ct_o_ex, jnp.array(True), jnp.array(True))
        back_flat, _ = sc.flat_program(self._vjp_step, ex_back, cut)
        n_lam = len(sc.split(lam0))
        n_acc = len(sc.split(acc0))

        def segment(carry, s_ck):
            flam, facc = carry
            s, fck = s_ck
            _, states = advance_flat(list(fck), s, True)
            j, cts, is_save = self._segment_cts(ct_obs, s)

            def back(carry, x):
                flam, facc = carry
                fc, ct_o, sv, jj = x
                flat = sc.split(P) + list(fc) + flam + facc + sc.split(ct_o) + [sv, jj < self.n]
                out = back_flat(flat)
                return (out[:n_lam], out[n_lam : n_lam + n_acc]), None

            (flam, facc), _ = jax.lax.scan(
                back, (flam, facc), (states, cts, is_save, j), reverse=True
            )
            return (flam, facc), None

        (flam, facc), _ = jax.lax.scan(
            segment, (sc.split(lam0), sc.split(acc0)), (jnp.arange(S), ck_flat), reverse=True
        )
        lam = sc.join(flam, jax.eval_shape(lambda: lam0))
        acc = sc.join(facc, jax.eval_shape(lambda: acc0))
        return acc, lam


# --------------------------------------------------------------------------
# linear_call under vmap
# --------------------------------------------------------------------------


def _register_linear_call_batching() -> bool:
    """Give ``linear_call`` a batching rule: vmap its program and its transpose.

    JAX (0.4 to 0.10 at least) has none, so ``vmap`` of a gradient through a
    ``linear_call`` raises ``NotImplementedError``. The rule batches the
    callee with every linear input and output batched, and its transpose (made
    lazily, as JAX does) with the residuals batched as given and every
    cotangent batched. Returns False when JAX's internals have moved (the
    engine then falls back to plain autodiff of the array program).
    """
    try:
        from jax._src import core, custom_derivatives as cd
        from jax._src.interpreters import batching, partial_eval as pe
    except ImportError:  # pragma: no cover - JAX internals moved
        return False
    p = getattr(cd, "linear_call_p", None)
    if p is None or not hasattr(batching, "fancy_primitive_batchers"):  # pragma: no cover
        return False
    if p in batching.fancy_primitive_batchers:
        return True

    def hoist(closed):
        if not closed.consts:
            return closed, []
        jaxpr = pe.convert_constvars_jaxpr(closed.jaxpr)
        return core.ClosedJaxpr(jaxpr, ()), list(closed.consts)

    def rule(axis_data, args, dims, *, callee, transpose_thunk, num_callee_consts, num_res):
        size = axis_data.size
        n_pre = num_callee_consts + num_res
        pre = [
            x if d is None else batching.moveaxis(x, d, 0)
            for x, d in zip(args[:n_pre], dims[:n_pre], strict=True)
        ]
        pre_b = [d is not None for d in dims[:n_pre]]
        lin = [
            batching.bdim_at_front(x, d, size)
            for x, d in zip(args[n_pre:], dims[n_pre:], strict=True)
        ]
        callee_b, _ = batching.batch_jaxpr(callee, axis_data, pre_b + [True] * len(lin), True)
        # linear_call evaluates its callee without consts: constants that batching
        # introduced (broadcasts, iotas) become leading callee-const arguments.
        callee_b, hoisted = hoist(callee_b)
        res_b = pre_b[num_callee_consts:]
        n_out = len(callee.out_avals)

        @pe._memoize
        def thunk():
            t_jaxpr, t_consts = transpose_thunk()
            in_b = [False] * len(t_consts) + res_b + [True] * n_out
            t_b, _ = batching.batch_jaxpr(t_jaxpr, axis_data, in_b, True)
            t_b, t_hoisted = hoist(t_b)
            return t_b, [*t_hoisted, *t_consts]

        out = p.bind(
            *hoisted,
            *pre,
            *lin,
            callee=callee_b,
            transpose_thunk=thunk,
            num_callee_consts=len(hoisted) + num_callee_consts,
            num_res=num_res,
        )
        return out, [0] * len(out)

    batching.fancy_primitive_batchers[p] = rule
    return True


_HAVE_LINEAR_CALL_BATCHING = _register_linear_call_batching()


# --------------------------------------------------------------------------
# the entry point
# --------------------------------------------------------------------------


_PROGRAMS = ("auto", "array", "scalar", "autodiff", "adjoint")


def run(
    step: Callable,
    observe: Callable,
    params,
    carry0,
    n_steps: int,
    save_every: int = 1,
    *,
    checkpoint: int | None = None,
    program: str = "auto",
):
    """Step ``carry0`` ``n_steps`` times; observe every ``save_every``-th state.

    **Arguments:**

    - `step`: ``step(params, carry) -> carry``, one step (pure; a carry may
      hold integer leaves such as a step counter and a status code).
    - `observe`: ``observe(params, carry) -> pytree`` of float arrays.
    - `params`: a pytree of arrays the loop depends on; its float leaves (and
      those of ``carry0``) are what derivatives flow to.
    - `n_steps`, `save_every`: Python ints, ``n_steps % save_every == 0``.
    - `checkpoint`: steps per checkpointed segment of the adjoint (default
      about ``sqrt(n_steps)``; ``n_steps`` keeps every state).
    - `program`: ``"auto"`` (the engine decides, see the module docstring);
      ``"array"`` or ``"scalar"`` (one layout for the forward run whatever the
      batching, derivatives from JAX's ``jvp`` of the checkpointed array
      program: for benchmarks); ``"autodiff"`` (the checkpointed array
      program, differentiated and batched by JAX alone: the reference);
      ``"adjoint"`` (derivatives from the engine's tangent program and, in
      reverse mode, always its discrete adjoint; layouts per `BATCHED_LAYOUT`).

    **Returns:** ``(observations, final carry)``; every observation leaf has a
    leading axis of length ``n_steps // save_every`` (the states after steps
    ``save_every, 2 save_every, ...``).
    """
    if program not in _PROGRAMS:
        raise ValueError(f"program must be one of {_PROGRAMS}, got {program!r}")
    K = checkpoint_length(n_steps) if checkpoint is None else int(checkpoint)
    # Closed-over tracers (a reference that closes over a traced amplitude, say)
    # become explicit parameters, so derivatives and batching see them.
    step_c, step_consts = jax.closure_convert(step, params, carry0)
    obs_c, obs_consts = jax.closure_convert(observe, params, carry0)
    P = (params, step_consts, obs_consts)

    def step_p(P, c):
        return step_c(P[0], c, *P[1])

    def obs_p(P, c):
        return obs_c(P[0], c, *P[2])

    loop = _Loop(step_p, obs_p, n_steps, save_every, K)
    if program == "autodiff":
        return loop.fwd_checkpointed(P, carry0)
    if program in ("auto", "adjoint") and _HAVE_LINEAR_CALL_BATCHING:
        return _adjoint_run(loop, P, carry0, reverse=program)
    if program == "array":
        fwd = loop.fwd_array
    elif program == "scalar":
        fwd = _dual(_scalar_or_array(loop), loop.fwd_scalar, "run")
    else:
        fwd = _dual(loop.fwd_array, loop.fwd_scalar, "run")

    # Derivatives: JAX's own jvp of the checkpointed array program (forward mode
    # as one fused scan; reverse mode by JAX's transpose, memory ~sqrt(n)).
    @jax.custom_jvp
    def f(P, c0):
        return fwd(P, c0)

    def _f_jvp(primals, tangents):
        # Only the inputs with nonzero tangents are differentiated: dense zero
        # tangents for every other array would add a tangent term to each
        # operation that touches them (35 % more time for DiffTune's jacfwd).
        p_leaves, treedef = jax.tree.flatten(primals)
        t_leaves = jax.tree.leaves(tangents, is_leaf=lambda t: isinstance(t, SymbolicZero))
        nz = [not isinstance(t, SymbolicZero) for t in t_leaves]

        def g(*xs):
            return loop.fwd_checkpointed(*jax.tree.unflatten(treedef, _fill(nz, xs, p_leaves)))

        xs = [p for p, z in zip(p_leaves, nz, strict=True) if z]
        ts = [t for t, z in zip(t_leaves, nz, strict=True) if z]
        return jax.jvp(g, xs, ts)

    f.defjvp(_f_jvp, symbolic_zeros=True)
    return f(P, carry0)


#: Reverse mode through at most this many differentiated scalars takes the
#: Jacobian's columns from the tangent program, one run each, instead of the
#: discrete adjoint (`_transpose_by_columns`).
FORWARD_JACOBIAN_MAX = 8


def _transpose_by_columns(linear: Callable, like: list, cts) -> list:
    """``J^T cts`` for ``linear = J`` (inputs shaped like ``like``), one column at a time.

    Each column is one run of the tangent program with a unit input (under
    `jax.lax.map`, so the program compiles once); with a handful of inputs this
    is cheaper than a backward pass: nothing is recomputed from checkpoints,
    and a batch runs the scalarized tangent program.
    """
    ends = np.cumsum([math.prod(jnp.shape(x)) for x in like]).tolist()
    ct_leaves = jax.tree.leaves(cts)

    def unflatten(vec):  # a flat vector as arrays shaped and typed like ``like``
        starts = [0] + ends[:-1]
        return [
            vec[a:b].reshape(jnp.shape(x)).astype(jnp.result_type(x))
            for a, b, x in zip(starts, ends, like, strict=True)
        ]

    def column(unit):
        col = jax.tree.leaves(linear(unflatten(unit)))
        return sum(jnp.sum(c * d) for c, d in zip(ct_leaves, col, strict=True))

    return unflatten(jax.lax.map(column, jnp.eye(ends[-1], dtype=jnp.result_type(*like))))


def _autodiff_transpose(loop: _Loop, nz: list, P, c0, ct_ys, ct_cN) -> list:
    """Reverse mode as JAX's transpose of the checkpointed array program.

    Only the float inputs flagged in ``nz`` are differentiated (the others are
    held at their primal values), as in `run`'s symbolic-zero rule.
    """
    pf, cf = _floats(P), _floats(c0)

    def g(*xs):
        full = _fill(nz, xs, pf + cf)
        Pp, cp = _with_floats(P, full[: len(pf)]), _with_floats(c0, full[len(pf) :])
        ys, cN = loop.fwd_checkpointed(Pp, cp)
        return ys, _floats(cN)

    xs = [x for x, z in zip(pf + cf, nz, strict=True) if z]
    return list(jax.vjp(g, *xs)[1]((ct_ys, list(ct_cN))))


def _adjoint_run(loop: _Loop, P, carry0, reverse: str = "adjoint"):
    """The run with the engine's own tangent program and a custom reverse mode.

    Forward mode is the tangent program (`_Loop.tan_array` / `_Loop.tan_scalar`).
    Reverse mode, ``reverse="adjoint"``: the discrete adjoint (`_Loop.adj_array`
    / `_Loop.adj_scalar`). ``reverse="auto"``: the Jacobian's columns from the
    tangent program when at most `FORWARD_JACOBIAN_MAX` scalars are
    differentiated (`_transpose_by_columns`), else JAX's transpose of the
    checkpointed array program (`_autodiff_transpose`).
    """
    fwd = _dual(loop.fwd_array, loop.fwd_scalar, "run")
    tan = _dual(loop.tan_array, loop.tan_scalar, "tangent")
    adj = _dual(loop.adj_array, loop.adj_scalar, "adjoint")

    @jax.custom_jvp
    def f(P, c0):
        return fwd(P, c0)

    def f_jvp(primals, tangents):
        P, c0 = primals
        out = fwd(P, c0)
        dP, dc0 = tangents
        tl = _floats_with_zeros((dP, dc0), (P, c0))
        nz = [not isinstance(t, SymbolicZero) for t in tl]
        lin = [t for t, z in zip(tl, nz, strict=True) if z]
        pf, cf = _floats(P), _floats(c0)

        def fill(lin):
            full = _fill(nz, lin, [jnp.zeros_like(x) for x in pf + cf])
            return full[: len(pf)], full[len(pf) :]

        def tangent(res, lin):
            P, c0 = res
            dPf, dcf = fill(lin)
            dys, dcN = tan(P, c0, dPf, dcf)
            return dys, dcN

        def transpose(res, cts):
            P, c0 = res
            ct_ys, ct_cN = cts
            if reverse == "auto":
                if sum(math.prod(jnp.shape(x)) for x in lin) <= FORWARD_JACOBIAN_MAX:
                    return _transpose_by_columns(
                        lambda lin_t: tangent(res, lin_t), lin, (ct_ys, list(ct_cN))
                    )
                return _autodiff_transpose(loop, nz, P, c0, ct_ys, ct_cN)
            gP, gc = adj(P, c0, ct_ys, ct_cN)
            return [g for g, z in zip(list(gP) + list(gc), nz, strict=True) if z]

        if not lin:
            dys = jax.tree.map(jnp.zeros_like, out[0])
            dcNf = [jnp.zeros_like(x) for x in _floats(out[1])]
        else:
            dys, dcNf = linear_call(tangent, transpose, (P, c0), lin)
        dcN = _tangent_tree(out[1], dcNf)
        return out, (dys, dcN)

    f.defjvp(f_jvp, symbolic_zeros=True)
    return f(P, carry0)


def _scalar_or_array(loop: _Loop) -> Callable:
    """The scalarized forward program, or the array one (with a warning) if it cannot be."""

    def fwd(P, c0):
        try:
            return loop.fwd_scalar(P, c0)
        except sc.ScalarizeError as e:
            warnings.warn(f"{e}; running the array program instead", stacklevel=4)
            return loop.fwd_array(P, c0)

    return fwd


def _floats_with_zeros(tangents, primals) -> list:
    """Tangents of the float leaves of ``primals`` (symbolic zeros kept)."""
    t_leaves = jax.tree.leaves(tangents, is_leaf=lambda x: isinstance(x, SymbolicZero))
    p_leaves = jax.tree.leaves(primals)
    return [t for t, p in zip(t_leaves, p_leaves, strict=True) if _is_float(p)]
