"""The engine's optimisation passes, one module each.

Every pass is a program transformation that leaves a run's results equal to the
reference path's (`so3jax._engine.loop`) to round-off, and each is switched by name in
the active `so3jax._engine.policy.Policy` (``policy.on(name)``):

- `scalarize`: a batch as a structure-of-arrays program of scalar components (the
  interpreter; `scalarized`: the programs of a loop it builds);
- `cuts`: fusion cuts where XLA on CPU would recompute shared values;
- `frames`: attitude tangents as three numbers in the Jacobian programs;
- `hoist`: each loop one kernel on a CPU;
- `unroll`: small reductions written out term by term;
- `tiles`: a batch of Jacobian programs in cache-sized tiles;
- `settle`: each loop starts where JAX's fixed point over its carry ends.

Each has a test module in ``tests/passes/`` proving its equality with the reference
under ``jit``, ``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian``, and a row in
``benchmarks/ablation.py`` measuring what it buys.
"""
