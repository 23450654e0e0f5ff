"""The tracking reward (paper Eq. 1 as shaped in the supplement), batched (torch or numpy),
every weight a config value.

``r = − w_track · (w_palm_pos·e_palm + w_palm_rot·e_palm_rot + w_joint·e_joint + w_tip·e_tip)``
``    + w_prox · proximity − w_goal · d_goal + w_bonus · bonus``
``    + w_success · success + w_object_success · object_success``  (per-frame success tests, 0 by default)

* tracking errors: palm position (m) and rotation (rad, :func:`adadex.quat.quat_diff` angle),
  mean absolute joint error (rad), mean fingertip position error (m);
* proximity: −min(d_palm, palm_clip) − gate · min(d_tip, tip_clip), distances from the robot's palm
  and fingertips (mean) to the object centre; the fingertip term is on only once the palm is within
  ``palm_gate`` of the object, and the whole term only while the reference hand is within
  ``contact_distance`` of the reference object (approach and contact phases of the reference —
  pulling the hand to the object while the reference hand is far away would fight the tracking);
* d_goal: object position error + ``goal_rot_weight`` · object rotation error;
* bonus: 1[e_palm ≤ τ_palm, e_tip ≤ τ_tip, d_goal ≤ τ_goal] · 1 / (1 + 10·d_goal).

Shaping for reinforcement learning (adadex's, not the paper's; set the weights to 0 for Eq. 1 alone):

``    + w_alive + w_hand_exp·exp(−(e_palm + e_tip)/σ_hand) + w_object_exp·exp(−d_goal/σ_object)``
``    + w_joint_exp·exp(−e_joint/σ_joint)``,  and ``− w_termination`` on the step an episode terminates.

**Hand tracking in the object's frame** (``object_frame`` in [0, 1], 1 by default): while the
reference hand is within ``contact_distance`` of the reference object, the palm and fingertip errors
are blended (weight ``object_frame``) towards their errors *relative to the object*,
``|(p − p_obj) − (p̂ − p̂_obj)|``. In the world frame alone, a policy that meets an object displaced
by the randomization (Table 3: x, y + N(0, 5 cm)) loses the hand-tracking terms for every centimetre
it moves to the object, so it keeps the hand on the reference and closes the grasp where the object
was meant to be (measured for replay on a mug: lifted in 22 % of the episodes with only the
displacement, in all without randomization). Relative to the object, grasping it where it lies
costs nothing; the object terms then pull it back onto its reference path. It is what the
object-anchored feed-forward (:mod:`adadex.modules.anchor`, on by default) does, so the two agree:
with the anchor, a specialist trained to 3 M frames kept T_o at 0.55 × replay's with it and drifted
to 0.83 × without (one seed each; docs/training-log.md). Without
the anchor it did not make a specialist carry the object more often; ``object_frame=0`` restores
the world frame.

Eq. 1 alone is negative unless tracking is already good, so ending an episode early is its best
policy (measured: PPO learned to push the palm away, episodes 27 → 6 steps). The alive term and the
positive tracking kernels make every tracked step worth more than no step, and the termination
penalty (charged by the env, which knows when an episode terminates) removes what is left of the
incentive; the kernels also give a gradient where the negative terms are flat (fine tracking).
"""

from __future__ import annotations

from dataclasses import dataclass

from adadex.arrays import namespace, to_float
from adadex.envs.frame_errors import Thresholds, frame_errors, frame_success
from adadex.errors import check_number, check_numbers


#: The reward's terms as the env reports them (``("privileged", "reward_terms", name)``), unweighted
#: except ``shaping`` (the weighted sum of the shaping terms) and ``termination`` (the penalty charged).
TERM_NAMES = ("tracking", "proximity", "goal", "bonus", "success", "object_success", "shaping", "termination")


@dataclass(frozen=True)
class RewardConfig:
    """Weights and thresholds of the tracking reward (lengths in m, angles in rad).

    Every number of :func:`tracking_reward` is a field here, so a run changes the reward by settings
    (``TrainConfig.reward``, ``reward.w_prox=1.0`` in the recipes) rather than by code; the terms are
    those of the module docstring. Setting the shaping weights (``w_alive`` … ``w_termination``) and
    ``object_frame`` to 0 leaves the paper's Eq. 1.

    Attributes:
        w_track: weight of the whole hand-tracking error (default 1).
        w_palm_pos: weight of the palm position error, per m (default 1).
        w_palm_rot: weight of the palm rotation error, per rad (default 0.1).
        w_joint: weight of the mean absolute joint error, per rad (default 0.1).
        w_tip: weight of the mean fingertip position error, per m (default 1).
        w_prox: weight of the proximity term, which pulls the palm and fingertips to the object in the
            reference's approach and contact phases (default 0.5).
        palm_clip: the palm's distance to the object counts up to this, m (default 0.2).
        tip_clip: the fingertips' mean distance to the object counts up to this, m (default 0.1).
        palm_gate: the fingertip proximity term is on only once the palm is this close to the object,
            m (default 0.08).
        contact_distance: proximity, and the object-frame hand errors, apply only while the reference
            hand is this close to the reference object, m (default 0.12).
        w_goal: weight of d_goal, the object's pose error (default 1).
        goal_rot_weight: d_goal = object position error + this · object rotation error, m per rad
            (default 0.1).
        w_bonus: weight of the bonus paid when palm, fingertips and object are all within their
            thresholds (default 1).
        tau_palm: the bonus's palm position threshold, m (default 0.05).
        tau_tip: the bonus's mean fingertip threshold, m (default 0.05).
        tau_goal: the bonus's d_goal threshold (default 0.05).
        w_alive: paid per step while the episode runs (shaping; default 0.5).
        w_hand_exp: weight of exp(−(palm + mean fingertip position error) / ``sigma_hand``)
            (shaping; default 0.5).
        sigma_hand: that kernel's length scale, m (default 0.05).
        w_object_exp: weight of exp(−d_goal / ``sigma_object``) (shaping; default 1).
        sigma_object: that kernel's length scale (default 0.05).
        w_joint_exp: weight of exp(−mean |joint error| / ``sigma_joint``) (shaping; default 0.25).
        sigma_joint: that kernel's scale, rad (default 0.1).
        w_termination: charged once when an episode terminates, not at truncation (default 10): it
            removes the incentive to end an episode early.
        w_success: paid per step on which the frame meets the paper's success thresholds — the frames
            completion counts (:func:`adadex.envs.frame_errors.frame_success`, world frame; default 0).
        w_object_success: paid per step on which the frame meets them with the object within 5 cm of
            its reference — the frames object completion counts
            (:func:`adadex.envs.frame_errors.object_success`; default 0). With 0 the return ranks
            episodes poorly against object completion; a few units make the two agree far better
            (docs/modulation.md, "The reward against the metric").
        object_frame: 0: palm and fingertip errors in the world frame; up to 1 (default 1): in
            contact phases, blended towards their errors relative to the object, so grasping a
            displaced object where it lies costs no hand tracking (see the module docstring).

    Example:
        >>> cfg = RewardConfig(w_object_success=3.0)
        >>> cfg.w_object_success, cfg.w_success, cfg.object_frame
        (3.0, 0.0, 1.0)
    """

    w_track: float = 1.0
    w_palm_pos: float = 1.0
    w_palm_rot: float = 0.1
    w_joint: float = 0.1
    w_tip: float = 1.0
    w_prox: float = 0.5
    palm_clip: float = 0.2
    tip_clip: float = 0.1
    palm_gate: float = 0.08
    contact_distance: float = 0.12
    w_goal: float = 1.0
    goal_rot_weight: float = 0.1
    w_bonus: float = 1.0
    tau_palm: float = 0.05
    tau_tip: float = 0.05
    tau_goal: float = 0.05
    # RL shaping (see the module docstring)
    w_alive: float = 0.5
    w_hand_exp: float = 0.5
    sigma_hand: float = 0.05
    w_object_exp: float = 1.0
    sigma_object: float = 0.05
    w_joint_exp: float = 0.25
    sigma_joint: float = 0.1
    w_termination: float = 10.0
    w_success: float = 0.0
    w_object_success: float = 0.0
    object_frame: float = 1.0

    def __post_init__(self):
        check_numbers("RewardConfig", self, self.__dict__)
        for k in ("sigma_hand", "sigma_object", "sigma_joint"):
            check_number(f"RewardConfig.{k}", getattr(self, k), strict_low=True)
        check_number("RewardConfig.object_frame", self.object_frame, high=1.0)


def tracking_reward(cfg: RewardConfig, *, joint_pos, link_pose, object_pose, ref_joint_pos, ref_link_pose,
                    ref_object_pose, errors: dict | None = None) -> tuple:
    """(B,) reward and its terms from (B, 22) joints, (B, 5, 7) link poses, (B, 7) object poses and
    the reference at the same frame. ``errors`` (the frame's metric errors, if already computed)
    saves recomputing the palm and object errors. Torch tensors or numpy arrays.

    Args:
        cfg: the reward's weights, clips and scales (:class:`RewardConfig`).
        joint_pos: (B, 22) joint positions, rad.
        link_pose: (B, 5, 7) palm and fingertip poses (position m + wxyz quaternion).
        object_pose: (B, 7) object pose.
        ref_joint_pos: (B, 22) the reference's joint positions at this frame.
        ref_link_pose: (B, 5, 7) the reference's link poses.
        ref_object_pose: (B, 7) the reference's object pose.
        errors: the frame's errors (``"T_o"``, ``"R_o"``, ``"T_h"``, ``"R_h"``, ``"E_finger"``), or
            None (default): computed here.

    Returns:
        ``(reward, terms)``: the (B,) reward and a dict of its (B,) unweighted terms
        (``tracking``, ``proximity``, ``goal``, ``bonus``, ``success``, ``object_success``,
        ``shaping``).
    """
    xp = namespace(joint_pos)
    # Every distance the reward needs, in one norm over stacked (B, 12, 3) differences.
    palm, tips, obj = link_pose[:, 0, :3], link_pose[:, 1:, :3], object_pose[:, None, :3]
    diffs = xp.concatenate([tips - ref_link_pose[:, 1:, :3],                       # 0–3  fingertip tracking
                       palm[:, None] - obj, tips - obj,                        # 4, 5–8  hand to object
                       (ref_link_pose[:, 0, :3] - ref_object_pose[:, :3])[:, None],  # 9  reference hand to object
                       (palm - ref_link_pose[:, 0, :3])[:, None],              # 10  palm tracking
                       obj - ref_object_pose[:, None, :3]], axis=1)            # 11  object tracking
    dist = xp.linalg.vector_norm(diffs, axis=-1)
    e_tip, d_palm, d_tip, d_ref = dist[:, 0:4].mean(axis=-1), dist[:, 4], dist[:, 5:9].mean(axis=-1), dist[:, 9]
    if errors is None:
        errors = frame_errors(object_pose, ref_object_pose, link_pose[:, 0], ref_link_pose[:, 0], joint_pos,
                              ref_joint_pos)
    e_palm, e_palm_rot, t_o, r_o = errors["T_h"], errors["R_h"], errors["T_o"], errors["R_o"]
    passed = frame_success(errors)
    success = to_float(passed, t_o)
    object_success = to_float(passed & (t_o <= Thresholds().object_position), t_o)
    gate = to_float(d_palm <= cfg.palm_gate, d_palm)
    near = to_float(d_ref <= cfg.contact_distance, d_palm)
    if cfg.object_frame > 0:            # hand errors relative to the object, in contact phases
        rel = xp.linalg.vector_norm(diffs[:, [0, 1, 2, 3, 10]] - diffs[:, 11:12], axis=-1)
        w = cfg.object_frame * near
        e_tip = e_tip + w * (rel[:, 0:4].mean(axis=-1) - e_tip)
        e_palm = e_palm + w * (rel[:, 4] - e_palm)
    e_joint = abs(joint_pos - ref_joint_pos).mean(axis=-1)
    tracking = cfg.w_palm_pos * e_palm + cfg.w_palm_rot * e_palm_rot + cfg.w_joint * e_joint + cfg.w_tip * e_tip

    proximity = -near * (xp.clip(d_palm, None, cfg.palm_clip) + gate * xp.clip(d_tip, None, cfg.tip_clip))

    d_goal = t_o + cfg.goal_rot_weight * r_o
    hit = (e_palm <= cfg.tau_palm) & (e_tip <= cfg.tau_tip) & (d_goal <= cfg.tau_goal)
    bonus = to_float(hit, d_goal) / (1.0 + 10.0 * d_goal)
    shaping = (cfg.w_alive + cfg.w_hand_exp * xp.exp(-(e_palm + e_tip) / cfg.sigma_hand)
               + cfg.w_object_exp * xp.exp(-d_goal / cfg.sigma_object)
               + cfg.w_joint_exp * xp.exp(-e_joint / cfg.sigma_joint))
    reward = (-cfg.w_track * tracking + cfg.w_prox * proximity - cfg.w_goal * d_goal + cfg.w_bonus * bonus
              + cfg.w_success * success + cfg.w_object_success * object_success + shaping)
    terms = {"tracking": tracking, "proximity": proximity, "goal": d_goal, "bonus": bonus, "success": success,
             "object_success": object_success, "shaping": shaping}
    return reward, terms
