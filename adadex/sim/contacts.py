"""Who touches a body, and how hard: the normal contact force on it, summed per touching geom.

Used to see why a grasp fails (``benchmarks/replay_grasp.py --contacts``): which links of the hand
press on the object while the fingers close, and whether they squeeze it or press it into the table.

Example
-------
>>> import mujoco
>>> from adadex.sim.scene import OBJECT_BODY, build_scene_model, home_state
>>> m = build_scene_model("cube_050")
>>> d = mujoco.MjData(m)
>>> d.qpos[:], d.ctrl[:] = home_state(m)
>>> for _ in range(120):
...     mujoco.mj_step(m, d)
>>> sorted(body_contact_forces(m, d, OBJECT_BODY))     # resting: only the table holds it up
['table']
"""

from __future__ import annotations

import mujoco
import numpy as np

from adadex.errors import ConfigError


def body_contact_forces(model: mujoco.MjModel, data: mujoco.MjData, body: int | str) -> dict[str, float]:
    """Normal force (N) on ``body`` from each geom touching it in ``data``'s current contacts.

    Keys are the other geoms' names (``geom<id>`` for unnamed ones); geoms of ``body`` itself never
    appear.

    Args:
        model: the compiled model.
        data: its data, after a step or ``mj_forward`` (the contacts are read, not recomputed).
        body: the body, by name or id.

    Returns:
        ``{geom name: normal force in N}``, summed over that geom's contacts with ``body``.

    Raises:
        ConfigError: (a ``ValueError``) a body name the model does not have, or an id out of range.
    """
    if isinstance(body, str):
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
        if bid < 0:
            raise ConfigError(f"body {body!r} is not in the model")
    else:
        bid = int(body)
        if not 0 <= bid < model.nbody:
            raise ConfigError(f"body id {bid} out of range (the model has {model.nbody} bodies)")
    out: dict[str, float] = {}
    f6 = np.zeros(6)
    for i in range(data.ncon):
        c = data.contact[i]
        b1, b2 = model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]
        if (b1 == bid) == (b2 == bid):
            continue
        other = c.geom2 if b1 == bid else c.geom1
        mujoco.mj_contactForce(model, data, i, f6)
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, other) or f"geom{other}"
        out[name] = out.get(name, 0.0) + float(f6[0])
    return out
