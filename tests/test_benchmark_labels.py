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


def _jaxpr_text(fn, *args) -> str:
    """The printed jaxpr: two programs are the same program when their texts are equal.
    (Traced without the ``"hoist"`` pass: the choice of a loop's form is made when a
    program is traced, and what is compared here is the layout.)"""
    import jax

    from so3jax import _engine

    try:
        with _engine.policy.using(passes=_engine.policy.current().passes - {"hoist"}):
            return str(jax.make_jaxpr(fn)(*args))
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

    default = _jaxpr_text(batch(), R0s)  # traced first: the cache holds the default
    with layouts["layout"]("array"):
        forced = _jaxpr_text(batch(), R0s)
    array = _jaxpr_text(batch(False), R0s)
    assert forced == array != default  # (64 runs: the default is the scalarized program)
    assert _jaxpr_text(batch(), R0s) == default  # the table is restored on exit


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

    def program(label, variants):
        return _jaxpr_text(tp["runner"](label, scene, 0.01, 3, variants=variants), R0s)

    default = program("RKMK4", sweep_variants)
    assert program("RKMK4 default", tp["VARIANTS"]) == default
    array = program("RKMK4 array", sweep_variants)
    assert array != default
    assert program("RKMK4", tp["VARIANTS"]) == array


def test_unrolled_step_loops_change_the_program_not_the_results(equations):
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

    def unrolls():  # the `unroll` of every scan in the traced run
        jaxpr = jax.make_jaxpr(run)(scene).jaxpr
        return [e.params["unroll"] for e in equations(jaxpr) if e.primitive.name == "scan"]

    plain = run(scene)
    assert unrolls() and set(unrolls()) == {1}
    with unroll["unrolled"](3):  # 7 steps: two unrolled iterations and a remainder
        assert _engine.policy.current().scan_unroll == 3
        assert 3 in unrolls()  # the step loop's scan (lowering repeats its body)
        np.testing.assert_allclose(run(scene), plain, rtol=0, atol=1e-13)
    assert _engine.policy.current().scan_unroll == 1 and set(unrolls()) == {1}


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
