"""so3jax leaves JAX's global state as it found it: its rule tables and its config.

Checked in a fresh interpreter: the tables are read after importing so3jax's
dependencies (equinox and diffrax define primitives of their own on import) and the JAX modules it
imports (which register JAX's own primitives when first imported), then after
importing so3jax and running ``vmap(grad(...))`` of a simulation, which goes through
every derivative path of the engine. No rule of a primitive that existed before is
replaced, and the only new primitives are so3jax's own (named ``so3jax_*``).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import json
    import jax
    jax.config.update("jax_enable_x64", True)
    import diffrax, equinox, optax  # noqa: F401  (their own primitives register here)
    # JAX's own modules that so3jax imports register JAX's primitives on first import.
    import jax.experimental.multihost_utils, jax.experimental.xla_metadata  # noqa: F401
    from jax.interpreters import ad, batching

    def tables():
        return {
            "batching": dict(batching.fancy_primitive_batchers),
            "jvp": dict(ad.primitive_jvps),
            "transpose": dict(ad.primitive_transposes),
        }

    def config():
        return {k: repr(v) for k, v in jax.config.values.items()}

    before, config_before = tables(), config()
    import jax.numpy as jnp
    import so3jax

    sc = so3jax.scenes.seed()
    R0 = so3jax.random_rotation(jax.random.PRNGKey(0), (3,))
    W0 = jnp.zeros((3, 3))

    def cost(k, R, W):
        return so3jax.expected_cost(sc, k[0], k[1], R[None], W[None], so3jax.RKMK4(), 1e-2, 4)

    k = jnp.array([8.81, 2.54])
    jax.block_until_ready(jax.jit(jax.vmap(jax.grad(cost), in_axes=(None, 0, 0)))(k, R0, W0))
    after, config_after = tables(), config()
    changed = {
        name: sorted(str(p) for p in b if p in after[name] and after[name][p] is not b[p])
        for name, b in before.items()
    }
    added = {name: sorted(str(p) for p in after[name] if p not in before[name]) for name in after}
    config_changed = sorted(k for k in config_before if config_before[k] != config_after.get(k))
    print(json.dumps({"changed": changed, "added": added, "config": config_changed}))
    """
)


def test_rule_tables_and_config_unchanged_by_import_and_use():
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, check=True, timeout=600
    ).stdout
    import json

    report = json.loads(out.strip().splitlines()[-1])
    assert report["changed"] == {"batching": [], "jvp": [], "transpose": []}, report
    for table, names in report["added"].items():
        assert all(name.startswith("so3jax_") for name in names), (table, names)
    assert "so3jax_linear_call" in report["added"]["batching"]
    assert report["config"] == ["jax_enable_x64"] or report["config"] == [], report
