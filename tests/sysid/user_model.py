"""A robot that is not adadex's, for the workbench's ``--model`` tests: a 2-joint arm (300 and 120
N·m/rad servos) carrying a 1-joint finger with tiny gains (3 N·m/rad), its own options (4 ms step,
implicitfast) and a home keyframe in a gravity-loaded pose."""

from __future__ import annotations

from pathlib import Path

TINY_ARM_MJCF = """
<mujoco model="tiny_arm">
  <compiler angle="radian"/>
  <option timestep="0.004" integrator="implicitfast"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <body name="upper" pos="0 0 0.5">
      <joint name="shoulder" axis="0 1 0" range="-1.5 1.5" armature="0.05" damping="0.5"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1.5"/>
      <body name="fore" pos="0.3 0 0">
        <joint name="elbow" axis="0 1 0" range="-2 2" armature="0.02" damping="0.2"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.025" mass="0.8"/>
        <body name="digit" pos="0.25 0 0">
          <joint name="finger" axis="0 0 1" range="-1 1" armature="0.001" damping="0.01"/>
          <geom type="capsule" fromto="0 0 0 0.06 0 0" size="0.008" mass="0.03"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position name="shoulder_servo" joint="shoulder" kp="300" kv="20" ctrlrange="-1.5 1.5" forcerange="-40 40"/>
    <position name="elbow_servo" joint="elbow" kp="120" kv="8" ctrlrange="-2 2" forcerange="-15 15"/>
    <position name="finger_servo" joint="finger" kp="3" kv="0.1" ctrlrange="-1 1"/>
  </actuator>
  <keyframe><key name="home" qpos="0.3 0.5 0.1" ctrl="0.3 0.5 0.1"/></keyframe>
</mujoco>
"""


def write_tiny_arm(directory) -> Path:
    """Write the model to ``directory/tiny_arm.xml`` and return the path."""
    path = Path(directory) / "tiny_arm.xml"
    path.write_text(TINY_ARM_MJCF)
    return path


def edited_arm(arm, edit, name: str):
    """The model at ``arm`` with ``edit(spec)`` applied (an ``MjSpec`` edit, as a user would make it: see
    :mod:`tests.sysid.hidden`), written beside it as ``name.xml`` at full precision: a
    :class:`~adadex.sim.model_source.ModelSource` of its own, which the diagnosis never sees."""
    import mujoco

    from adadex.sim.model_source import ModelSource, _full_precision

    spec = mujoco.MjSpec.from_file(str(arm))
    edit(spec)
    path = Path(arm).parent / f"{name}.xml"
    path.write_text(_full_precision(spec.to_xml(), spec.compile()))
    return ModelSource(path)


def arm_recording(arm, truth, excited, *, measured=None, freqs=(0.5, 2.0), amps=(0.3, 1.0), kinds=("sine", "chirp"),
                  duration=2.0, noise=2e-4, seed=0, nthread=1):
    """A recording of the model at ``arm`` (its joint table: the diagnosis replays on ``arm``) in which
    ``excited`` move one at a time from its home pose while the other ``measured`` joints (default all)
    hold it, simulated on ``truth`` (a :class:`~adadex.sim.model_source.ModelSource`, e.g. an
    :func:`edited_arm`) after a 2 s pre-roll at rest, with N(0, ``noise``²) sensor noise, seeded."""
    import numpy as np

    from adadex.sim.model_source import ModelSource
    from adadex.sysid.excite import ExcitationPlan, design_excitation
    from adadex.sysid.replay import Replayer

    robot = ModelSource(arm).robot()
    measured = list(robot.names if measured is None else measured)
    plan = design_excitation(excited, freqs=freqs, amps=amps, kinds=kinds, duration=duration, robot=robot)
    cmd = np.repeat(plan.initial_qpos[:, None, :], len(plan.time), axis=1)
    cmd[:, :, robot.index(excited)] = plan.command
    full = ExcitationPlan(time=plan.time, joint_names=tuple(measured), command=cmd[:, :, robot.index(measured)],
                          initial_qpos=plan.initial_qpos, sequences=plan.sequences, robot=robot)
    proto = full.to_recording(full.command.copy())
    q = Replayer(proto, model=truth, preroll_s=2.0, nthread=nthread).simulate()
    q = q + np.random.default_rng(seed).normal(0.0, noise, size=q.shape)
    return full.to_recording(q, {"noise_rad": noise, "seed": seed})
