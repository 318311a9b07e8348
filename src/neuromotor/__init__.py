"""neuromotor: motion perturbation with simple neuromotor control models (Yin, Cline & Pai 2003).

Physics runs in float64: importing the package turns on ``jax_enable_x64``, unless the user has
chosen (``JAX_ENABLE_X64`` set in the environment, which JAX reads itself). With x64 off, a
float64 simulation is refused with a one-line error rather than run in float32 unasked;
``[sim] dtype = "float32"`` still runs.

The pipeline follows the paper: BVH -> body model -> kinematics -> inverse dynamics -> step ->
fit / sweep -> pictures (``docs/architecture.md``). Where each equation lives:

==========================================  ==========================================================
paper                                       function
==========================================  ==========================================================
Eq. 1, M, J, H in maximal coordinates       :func:`neuromotor.physics.system.kkt_matrix`
Eq. 2, linearly implicit step               :func:`step` (stages in :mod:`neuromotor.physics.dynamics`;
                                            solvers in :mod:`neuromotor.physics.solvers`)
post-stabilization (Cline & Pai 2003)       :func:`neuromotor.physics.constraints.post_stabilize`
Eq. 3, inverse dynamics                     :func:`inverse_dynamics`
discrete inverse dynamics (default)         :func:`discrete_inverse_dynamics` (the step's exact inverse)
Eq. 4, H^T tau = sum_i h_i tau_i            :func:`neuromotor.physics.system.dof_axes`,
                                            :func:`neuromotor.physics.control.joint_torque_magnitude`
Section 5.2, feedforward + feedback         :func:`neuromotor.physics.control.joint_torque`
gains scaled by distal inertia              :func:`make_gains`
K = dk/dx, D = dk/dv (closed form)         :mod:`neuromotor.physics.stiffness` (``jax.jacfwd`` the check)
Section 4, contact as an LCP                :mod:`neuromotor.physics.contact`
recovery metrics (Section 6)                :func:`recovery_metrics`
==========================================  ==========================================================

The names below are the curated public API; they are imported on first use, so that
``import neuromotor`` stays quick for the command line.
"""

import importlib
import os

import jax

if "JAX_ENABLE_X64" not in os.environ:  # the user's explicit choice stands
    jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"

# public name -> module that defines it
_API = {
    # configuration and errors
    "SimulationConfig": "neuromotor.config",
    "DEFAULT_HIT": "neuromotor.config",
    "load_simulation_config": "neuromotor.config",
    "UserError": "neuromotor.errors",
    "ConfigError": "neuromotor.errors",
    # BVH -> body model -> kinematics
    "read_bvh": "neuromotor.model.bvh",
    "parse_bvh": "neuromotor.model.bvh",
    "build_character": "neuromotor.model.skeleton",
    "Model": "neuromotor.model.skeleton",
    "Character": "neuromotor.model.skeleton",
    "Trajectory": "neuromotor.model.kinematics",
    "load_character": "neuromotor.model.load",
    # physics: inverse dynamics, controller, step, rollout
    "inverse_dynamics": "neuromotor.physics.inverse",
    "discrete_inverse_dynamics": "neuromotor.physics.discrete",
    "Gains": "neuromotor.physics.control",
    "make_gains": "neuromotor.physics.control",
    "pd_tracking_gains": "neuromotor.physics.control",
    "ForcePulses": "neuromotor.physics.perturbation",
    "State": "neuromotor.physics.system",
    "Solver": "neuromotor.physics.solvers",
    "Precision": "neuromotor.physics.precision",
    "StepOptions": "neuromotor.physics.dynamics",
    "Feedforward": "neuromotor.physics.options",
    "JointLaw": "neuromotor.physics.options",
    "Reference": "neuromotor.physics.dynamics",
    "make_reference": "neuromotor.physics.dynamics",
    "SimModel": "neuromotor.physics.dynamics",
    "Params": "neuromotor.physics.dynamics",
    "Data": "neuromotor.physics.dynamics",
    "init_data": "neuromotor.physics.dynamics",
    "step": "neuromotor.physics.dynamics",
    "simulate": "neuromotor.physics.dynamics",
    "rollout": "neuromotor.physics.dynamics",
    "Rollout": "neuromotor.physics.dynamics",
    "check_rollout": "neuromotor.physics.dynamics",
    "SimulationDiverged": "neuromotor.physics.dynamics",
    # studies
    "prepare": "neuromotor.studies.simulate",
    "run": "neuromotor.studies.simulate",
    "Setup": "neuromotor.studies.simulate",
    "RunResult": "neuromotor.studies.simulate",
    "gains_for": "neuromotor.studies.gains",
    "recovery_metrics": "neuromotor.studies.metrics",
    "load_calibration": "neuromotor.studies.fit",
    "calibrate": "neuromotor.studies.fit",
    "sweep_from_config": "neuromotor.studies.sweep",
    "use_cpu_cores": "neuromotor.compiler",  # before JAX starts: sweeps split over the cores
    "run_experiment": "neuromotor.studies.experiments",
    # files and pictures
    "run_arrays": "neuromotor.studies.record",
    "write_run": "neuromotor.io.runfile",
    "read_run": "neuromotor.io.runfile",
    "render_run": "neuromotor.viz.render",
    "plot_run": "neuromotor.viz.render",
    "write_viewer": "neuromotor.viz.html",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'neuromotor' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_API))
