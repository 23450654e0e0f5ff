"""MuJoCo layer: robot, objects, scene, batched simulator, model effects and patches. Imports
nothing from upper layers.

The names below are re-exported here (``from adadex.sim import BatchedSim, ModelPatch``) and imported
on first use.
"""

from typing import TYPE_CHECKING

from adadex._exports import lazy_exports

_EXPORTS = {
    "adadex.sim.batched": ("BatchedSim", "SimReadout"),
    "adadex.sim.robot": ("JOINT_NAMES", "NUM_JOINTS", "TRACKED_SITES", "HOME_QPOS",
                         "joint_limits", "effort_limits", "export_mjcf"),
    "adadex.sim.scene": ("CONTROL_HZ", "PHYSICS_TIMESTEP", "SUBSTEPS", "build_scene_model",
                         "build_scene_spec", "home_state", "PhysicsOptions"),
    "adadex.sim.objects": ("OBJECT_NAMES", "get_object", "held_out_objects"),
    "adadex.sim.effects": ("EFFECT_NAMES", "Effect", "get_effect"),
    "adadex.sim.patch": ("ModelPatch", "patched_scene"),
    "adadex.sim.model_source": ("ModelSource", "export_world"),
    "adadex.sim.kinematics": ("RobotKinematics",),
    "adadex.sim.grasp": ("scripted_grasp_lift",),
    "adadex.sim.contacts": ("body_contact_forces",),
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

if TYPE_CHECKING:      # the same names, for type checkers and IDEs
    from adadex.sim.batched import BatchedSim, SimReadout
    from adadex.sim.robot import (
        JOINT_NAMES, NUM_JOINTS, TRACKED_SITES, HOME_QPOS, joint_limits, effort_limits, export_mjcf
    )
    from adadex.sim.scene import (
        CONTROL_HZ, PHYSICS_TIMESTEP, SUBSTEPS, build_scene_model, build_scene_spec, home_state,
        PhysicsOptions
    )
    from adadex.sim.objects import OBJECT_NAMES, get_object, held_out_objects
    from adadex.sim.effects import EFFECT_NAMES, Effect, get_effect
    from adadex.sim.patch import ModelPatch, patched_scene
    from adadex.sim.model_source import ModelSource, export_world
    from adadex.sim.kinematics import RobotKinematics
    from adadex.sim.grasp import scripted_grasp_lift
    from adadex.sim.contacts import body_contact_forces
