"""The benchmark scripts measure what their labels say.

Apart from `test_benchmarks.py`, whose quick runs share one xdist worker (`--dist loadfile`).
"""

import runpy
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"


def _bench_module(name):
    """A benchmark script imported as a module (its folder on the path for ``_common``)."""
    path = list(sys.path)
    sys.path.insert(0, str(BENCH))
    try:
        return runpy.run_path(str(BENCH / f"{name}.py"), run_name=f"bench_{name}")
    finally:
        sys.path[:] = path


def _jaxpr_size(fn, *args) -> int:
    """The printed jaxpr's length, with the engine's loops as XLA would run them by
    default: a hoisted array program's reductions are written out
    (`_engine.passes.unroll._unrolled`),
    which makes it the larger one."""
    import jax

    from so3jax import _engine

    try:
        with _engine.policy.using(passes=_engine.policy.current().passes - {"hoist"}):
            return len(str(jax.make_jaxpr(fn)(*args)))
    finally:
        jax.clear_caches()  # (the choice is made when a program is traced)


def test_layouts_forces_the_array_program():
    """`layouts.layout("array")` changes the traced program, also after a default trace.

    JAX caches the batched jaxpr of the jitted functions inside `simulate`: editing the
    table without clearing those caches leaves "array" rows running the default program.
    The forced layout must trace what ``scalarize=False`` traces.
    """
    import jax

    import so3jax as s

    layouts = _bench_module("layouts")
    scene = s.scenes.seed()
    R0s = s.random_rotation(jax.random.key(0), (64,))

    def batch(scalarize=None):
        return jax.vmap(
            lambda R0: s.simulate(scene, s.RKMK4(), 0.01, 3, 3, scalarize=scalarize, R0=R0).R
        )

    default = _jaxpr_size(batch(), R0s)  # traced first: the cache holds the default
    with layouts["layout"]("array"):
        forced = _jaxpr_size(batch(), R0s)
    array = _jaxpr_size(batch(False), R0s)
    assert forced < 0.8 * default  # the scalarized program is the larger jaxpr
    assert abs(forced - array) < 0.05 * array
    assert _jaxpr_size(batch(), R0s) == default  # the table is restored on exit


def test_throughput_sweep_labels():
    """In the throughput sweep a method's name is the default program; ``RKMK4 array``
    forces the array program; in the equal-accuracy part ``RKMK4`` is the array program."""
    import jax

    import so3jax as s

    old_argv = sys.argv
    sys.argv = ["throughput.py"]
    try:
        tp = _bench_module("throughput")
    finally:
        sys.argv = old_argv
    scene = s.scenes.seed()
    R0s = s.random_rotation(jax.random.key(0), (64,))
    sweep_variants = tp["SWEEP_LABELS"]
    assert "RKMK4" not in sweep_variants and "RKMK4" in tp["VARIANTS"]

    def size(label, variants):
        return _jaxpr_size(tp["runner"](label, scene, 0.01, 3, variants=variants), R0s)

    default = size("RKMK4", sweep_variants)
    assert size("RKMK4 default", tp["VARIANTS"]) == default
    array = size("RKMK4 array", sweep_variants)
    assert array < 0.8 * default
    assert size("RKMK4", tp["VARIANTS"]) == array


def test_unrolled_step_loops_change_the_program_not_the_results():
    """`unroll.unrolled(u)` traces the engine's step loops unrolled (a larger lowered
    program, also after a trace with the default) and leaves the run as it was. (Not
    differentiated here: a gradient through the unrolled loop compiles for 12 s, and
    ``scan_unroll`` is a benchmark setting, 1 by default.)"""
    import jax
    import numpy as np

    import so3jax as s
    from so3jax import _engine

    unroll = _bench_module("unroll")
    scene = s.scenes.seed()

    def run(scene):
        return s.simulate(scene, s.RKMK4(), 0.01, 7, 1).R

    def lowered_size():  # the jaxpr holds `unroll` as a parameter; lowering repeats the body
        return len(jax.jit(run).lower(scene).as_text())

    plain, size = run(scene), lowered_size()
    with unroll["unrolled"](3):  # 7 steps: two unrolled iterations and a remainder
        assert _engine.policy.current().scan_unroll == 3
        assert lowered_size() > size  # the step (a called function) appears 3 times
        np.testing.assert_allclose(run(scene), plain, rtol=0, atol=1e-13)
    assert _engine.policy.current().scan_unroll == 1 and lowered_size() == size


def test_vehicle_configurations_hold_their_models():
    """`vehicle.py`'s "plain, models off" (every model given, off) traces the very program
    of the plain quadrotor; "full vehicle" holds every model, "rotors" only its own, and the
    target's configuration lagged rotors and drag."""
    import jax
    import jax.numpy as jnp

    import so3jax as s

    veh = _bench_module("vehicle")
    n, dtype = 3, jnp.float64
    args = veh["inputs"](4, n, dtype)

    def scene(config):
        return veh["scene"](config, dtype, n * veh["DT"])

    def jaxpr(config):
        try:
            return str(jax.make_jaxpr(veh["batch"](scene(config), n))(*args))
        finally:
            jax.clear_caches()  # (the engine's choices are made when a program is traced)

    plain = jaxpr("plain")
    assert jaxpr("plain, models off") == plain
    assert jaxpr("rotors") != plain
    full, rotors = scene("full vehicle"), scene("rotors")
    assert full.rotors.lagged and full.integral and full.drag is not None
    assert isinstance(full.wind, s.Gust) and full.noise is not None
    assert not rotors.rotors.lagged and rotors.drag is None and rotors.wind is None
    assert not rotors.integral and getattr(rotors, "noise", None) is None
    aim = scene(veh["TARGET_CONFIG"])  # the models the target is for: lagged rotors and drag
    assert aim.rotors.lagged and aim.drag is not None and not callable(aim.wind)
    assert not aim.integral and getattr(aim, "noise", None) is None
