"""Ready-made scenes for `so3jax.simulate` (public namespace ``so3jax.scenes``)."""

from ._scene import MechanicalScene as MechanicalScene, Scene as Scene
from ._scenes import FreeBody as FreeBody, free_body as free_body
