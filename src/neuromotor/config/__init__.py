"""Configuration files: one TOML schema, parsed in one place into frozen, typed specs.

Simulation config (every table and key optional)::

    clip = "path/to/clip.bvh"      # default: the embedded clip; relative to the config file
    units = "auto"                 # auto | m | cm | mm | in | cmu | ft | metres per unit
    up_axis = "auto"               # auto (from the motion) | 0 | 1 | 2: gravity along -up
    stature = 1.75                 # m; default: estimated from the long bones
    body_mass = 70.0               # kg; default: BMI 22 at the stature
    sex = "average"                # de Leva's segment table: male | female | average
    simulate_extremities = false   # fingers, toes, face joints as simulated bodies

    [sim]
    h = 0.008333333333333333       # time step (s); amplitudes carry a first-order error (docs/discrete.md)
    start = 0.0                    # clip time of the first step (s)
    duration = 3.0                 # simulated seconds (default: to the clip's end; with still,
                                   # the clip's duration, and any duration is allowed)
    still = 1.25                   # optional: the capture's pose at this clip time (s), held
                                   # still with zero velocity over the whole window (the
                                   # feedforward holds it against gravity); start and the
                                   # perturbations' times are then the window's own clock
    implicit = true                # linearly implicit step (false: K = D = 0)
    driven_joints = []             # bodies driven along the mocap like the root: body names or
                                   # trunk | pelvis | legs | arms | head (every body with those
                                   # segment labels, as `neuromotor inspect` prints them) or a
                                   # single body: chest | left_hand ...; ["trunk", "pelvis"]:
                                   # a belted torso on any rig
    stabilization_steps = 2        # Newton steps of post-stabilization per step (1..5): 2 (a
                                   # projection, then a closing step) reach round-off; 1 (the
                                   # projection only, as Cline & Pai) leaves up to ~4e-8 m
    dtype = "float64"              # float64 | float32 (sweeps, accelerators; docs/float32.md)
    feedforward = "discrete"       # discrete: the exact inverse of the step (the unperturbed run
                                   # replays the capture) | continuous: the paper's Eq. 3
    joint_law = "rotation"         # rotation: each ball joint's torque and error as one 3-vector
                                   # (the same for every Euler order) | euler: the paper's per DOF
    metric = "geodesic"            # the deviation d(t) and every figure from it: geodesic (RMS
                                   # over joints of each joint's rotation angle) | euler (RMS
                                   # over the Euler DOFs; about 1/sqrt(3) of it, gimbal artefacts)

    [gains]
    ks = 400.0                     # 1/s^2 (see neuromotor.physics.control for the scaling)
    kd = 20.0                      # 1/s
    tau_floor = 0.5                # fraction of each DOF's RMS feedforward torque

    [[perturbation]]               # any number of these
    kind = "force"                 # force | impulse
    body = "Chest2"                # a body (joint) name, or chest | pelvis | head | left_hand ...
    point = [0.0, 0.1, 0.0]        # body frame, m, from the joint origin (default: its COM)
    direction = [1.0, 0.0, 0.0]    # world
    magnitude = 150.0              # N (force) or N s (impulse)
    start = 1.0                    # s, clip time
    duration = 0.1                 # s (force only)
    shape = "half_sine"            # square | half_sine | triangle

    [ball]                         # a flying ball (see neuromotor.physics.contact); optional
    radius = 0.11                  # m
    mass = 0.45                    # kg
    position = [1.5, 1.3, 2.3]     # world centre at launch (m)
    speed = 12.0                   # m/s, with either target (a body to aim at) or direction,
    target = "Chest2"              #   or give velocity = [vx, vy, vz] instead of speed
    launch = 1.0                   # s, clip time of release
    restitution = 0.6              # Newton's coefficient, 0..1
    friction = 0.5                 # Coulomb coefficient
    restitution_threshold = 0.25   # m/s: slower impacts do not bounce
    friction_directions = 8        # sides of the friction pyramid (>= 4)
    max_contacts = 4               # nearest contact candidates solved per step
    pgs_iterations = 40            # projected Gauss-Seidel sweeps
    ground = true                  # the ball also hits the ground plane (up . x = ground_height)
    ground_height = 0.0

``[fit]`` (docs/fitting.md), ``[sweep]`` (:mod:`neuromotor.studies.sweep`) and ``[experiment]``
(:mod:`neuromotor.studies.experiments`) are parsed by the same module, :mod:`neuromotor.config.parse`.
"""

from neuromotor.config.fields import Fields, read_toml
from neuromotor.config.parse import (
    experiment_spec,
    fit_spec,
    load_experiment,
    load_simulation_config,
    load_sweep_config,
    parse_ball,
    parse_perturbation,
    read_fitted,
    simulation_config,
    sweep_spec,
)
from neuromotor.config.specs import (
    CONTROLLERS,
    DEFAULT_CONTRAST,
    DEFAULT_HIT,
    FEATURE_NAMES,
    FIT_SOLVERS,
    TARGET_KINDS,
    BallSpec,
    ExperimentSpec,
    FeatureTarget,
    FitSpec,
    FitTargetSpec,
    GainSetting,
    PerturbationSpec,
    ReflexSpec,
    SimulationConfig,
    SolverOptions,
    Surrogate,
    SweepSpec,
)
from neuromotor.errors import ConfigError, UserError

__all__ = [
    "BallSpec",
    "CONTROLLERS",
    "ConfigError",
    "DEFAULT_CONTRAST",
    "DEFAULT_HIT",
    "ExperimentSpec",
    "FEATURE_NAMES",
    "FeatureTarget",
    "Fields",
    "FitSpec",
    "FitTargetSpec",
    "GainSetting",
    "PerturbationSpec",
    "ReflexSpec",
    "FIT_SOLVERS",
    "SimulationConfig",
    "SolverOptions",
    "Surrogate",
    "SweepSpec",
    "TARGET_KINDS",
    "UserError",
    "experiment_spec",
    "fit_spec",
    "load_experiment",
    "load_simulation_config",
    "load_sweep_config",
    "parse_ball",
    "parse_perturbation",
    "read_fitted",
    "read_toml",
    "simulation_config",
    "sweep_spec",
]
