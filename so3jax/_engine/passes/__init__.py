"""The engine's optimisation passes, one module each.

Each pass is a program transformation that leaves a run's results equal to the reference
path's (`so3jax._engine.loop`) to round-off, switched by name in the active
`so3jax._engine.policy.Policy` (``policy.on(name)``):

- `scalarize`: a batch as a structure-of-arrays program of scalar components (`scalarized`:
  the programs of a loop it builds);
- `cuts`: fusion cuts where XLA on CPU would recompute shared values;
- `frames`: attitude tangents as three numbers in the Jacobian programs;
- `hoist`: each loop one kernel on a CPU;
- `unroll`: small reductions written out term by term;
- `tiles`: a batch of Jacobian programs in cache-sized tiles;
- `settle`: each loop starts where JAX's fixed point over its carry ends.

``tests/passes/test_pass_<name>.py`` proves each equal to the reference under ``jit``,
``vmap``, ``grad``, ``jacfwd`` and ``jax.hessian``; ``benchmarks/ablation.py`` measures each.
"""
