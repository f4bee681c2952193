"""Ready-made scenes for `so3jax.simulate` (public namespace ``so3jax.scenes``)."""

from ._quadrotor import (
    Quadrotor as Quadrotor,
    quadrotor as quadrotor,
    quadrotor_circle as quadrotor_circle,
    quadrotor_flip as quadrotor_flip,
    quadrotor_recovery as quadrotor_recovery,
)
from ._scene import MechanicalScene as MechanicalScene, Scene as Scene
from ._scenes import (
    SEED_DURATION as SEED_DURATION,
    SEED_GAINS as SEED_GAINS,
    SEED_INERTIA as SEED_INERTIA,
    UNWINDING_ANGLE as UNWINDING_ANGLE,
    UNWINDING_RATE as UNWINDING_RATE,
    FreeBody as FreeBody,
    SampledTracking as SampledTracking,
    Tracking as Tracking,
    dzhanibekov as dzhanibekov,
    free_body as free_body,
    near_pi as near_pi,
    seed as seed,
    tracking as tracking,
    unwinding as unwinding,
)
from ._suslov import (
    SUSLOV_CONSTRAINT_RTOL as SUSLOV_CONSTRAINT_RTOL,
    Suslov as Suslov,
    suslov as suslov,
    suslov_project as suslov_project,
)
