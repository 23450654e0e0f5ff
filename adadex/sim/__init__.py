"""MuJoCo layer: robot, objects, scene, batched simulator. Imports nothing from upper layers."""

from adadex.sim.batched import BatchedSim, SimReadout
from adadex.sim.robot import JOINT_NAMES, NUM_JOINTS, TRACKED_SITES
from adadex.sim.scene import CONTROL_HZ, PHYSICS_TIMESTEP, SUBSTEPS, build_scene_model, build_scene_spec, home_state

__all__ = [
    "BatchedSim", "SimReadout", "JOINT_NAMES", "NUM_JOINTS", "TRACKED_SITES", "CONTROL_HZ",
    "PHYSICS_TIMESTEP", "SUBSTEPS", "build_scene_model", "build_scene_spec", "home_state",
]
