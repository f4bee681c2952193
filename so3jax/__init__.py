"""so3jax: rigid-body attitude dynamics and control on SO(3), in JAX."""

from . import scenes as scenes
from ._ambient import RK4 as RK4, simulate_ambient as simulate_ambient
from ._control import (
    AbstractController as AbstractController,
    AbstractReference as AbstractReference,
    ConingRate as ConingRate,
    ConstantRate as ConstantRate,
    GeometricController as GeometricController,
    GeometricGains as GeometricGains,
    QuaternionController as QuaternionController,
    SinusoidalRate as SinusoidalRate,
    geometric_torque as geometric_torque,
    tracking_errors as tracking_errors,
)
from ._dynamics import RigidBody as RigidBody
from ._integrators import (
    CF4 as CF4,
    CG3 as CG3,
    LGVI as LGVI,
    RKMK as RKMK,
    RKMK4 as RKMK4,
    RKMK32 as RKMK32,
    RKMK45 as RKMK45,
    AbstractLieSolver as AbstractLieSolver,
    ButcherTableau as ButcherTableau,
    CFTableau as CFTableau,
    CommutatorFree as CommutatorFree,
    DiffraxLieAdaptiveSolver as DiffraxLieAdaptiveSolver,
    DiffraxLieSolver as DiffraxLieSolver,
    LieEuler as LieEuler,
    LieTerm as LieTerm,
    RKMKTsit5 as RKMKTsit5,
    diffrax_solver as diffrax_solver,
    lie_term as lie_term,
)
from ._simulate import Status as Status, Trajectory as Trajectory, simulate as simulate
from ._so3 import (
    adjoint as adjoint,
    attitude_error_function as attitude_error_function,
    bracket as bracket,
    coadjoint as coadjoint,
    euler_zyx_rate_matrix as euler_zyx_rate_matrix,
    exp as exp,
    from_axis_angle as from_axis_angle,
    from_euler_zyx as from_euler_zyx,
    from_quat as from_quat,
    geodesic_distance as geodesic_distance,
    hat as hat,
    is_gimbal_locked as is_gimbal_locked,
    left_jacobian as left_jacobian,
    left_jacobian_inv as left_jacobian_inv,
    log as log,
    orthogonality_error as orthogonality_error,
    project as project,
    quat_multiply as quat_multiply,
    random_rotation as random_rotation,
    right_jacobian as right_jacobian,
    right_jacobian_inv as right_jacobian_inv,
    to_axis_angle as to_axis_angle,
    to_euler_zyx as to_euler_zyx,
    to_quat as to_quat,
    vee as vee,
)
from ._state import LieState as LieState, LieTangent as LieTangent
from ._sweep import SweepResult as SweepResult, initial_states as initial_states, sweep as sweep
from ._tune import (
    CostWeights as CostWeights,
    TuneResult as TuneResult,
    expected_cost as expected_cost,
    rollout_cost as rollout_cost,
    tracking_cost as tracking_cost,
    tune as tune,
)

__version__ = "0.1.0"
