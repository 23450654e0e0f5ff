"""Tests of the dataset build (the ``tiny`` preset, built once per module) and the feasibility filter."""

import dataclasses
import json

import numpy as np
import pytest

from adadex.data import feasibility
from adadex.data.build import PRESETS, build_dataset, make_splits, plan_instructions
from adadex.data.feasibility import REASONS, KinematicReplay, Rejection, check
from adadex.data.object_contact import PAD_GEOMS, TIP_GEOMS, ObjectContact, hand_object_overlap
from adadex.data.reference import WINDOW_FRAMES, Reference, ReferenceDataset
from adadex.data.synth import VERBS
from adadex.sim.objects import get_object, held_out_objects
from adadex.sim.robot import HOME_QPOS, JOINT_NAMES

SEED = 4   # = conftest.TINY_SEED: the session dataset is built with it


pytestmark = pytest.mark.usefixtures("one_torch_thread")   # tests/data/conftest.py


@pytest.fixture(scope="module")
def tiny(tiny_build):
    """(report, dataset) of the tiny preset (built once per session, see conftest)."""
    report, out = tiny_build
    return report, ReferenceDataset(out)


# ------------------------------------------------------------------------------------------------
# The built dataset


def test_dataset_opens_and_validates(tiny):
    report, ds = tiny
    assert report.path == str(ds.path)
    assert len(ds) == report.accepted > 0
    assert report.candidates == PRESETS["tiny"].base_instructions * PRESETS["tiny"].paraphrases
    assert report.accepted + sum(report.rejected.values()) == report.candidates
    assert report.retargeted_frames > 0 and {"synthesize", "retarget", "check", "save"} <= set(report.seconds)
    names = set()
    for ref in ds:
        ref.validate()
        names.add(ref.name)
        assert ref.object_name in PRESETS["tiny"].objects
        assert ref.human_keypoints is not None and ref.human_keypoints.shape == (ref.num_frames, 21, 3)
        assert ref.retarget_residual is not None and ref.retarget_residual.shape == (ref.num_frames,)
        assert np.isfinite(ref.retarget_residual).all() and (ref.retarget_residual >= 0).all()
        assert ref.num_frames >= WINDOW_FRAMES
        assert ref.instruction and ref.meta["verb"] in ref.name
        assert ref.meta["retarget_palm_error_max"] <= feasibility.FeasibilityConfig().max_palm_error
    assert len(names) == len(ds)


def test_index_info_holds_the_report(tiny):
    report, ds = tiny
    info = json.loads((ds.path / "index.json").read_text())["info"]
    assert info == ds.info
    assert info["preset"] == "tiny" and info["seed"] == SEED
    stored = info["report"]
    assert stored["accepted"] == report.accepted and stored["candidates"] == report.candidates
    assert stored["rejected"] == dict(report.rejected)
    assert set(stored["rejected"]) <= set(REASONS)
    assert len(stored["rejections"]) == sum(stored["rejected"].values())
    accepted = {e["name"] for e in ds.entries}
    for r in stored["rejections"]:
        assert r["reason"] in REASONS and r["detail"]
        assert r["name"] not in accepted
        assert r["frame"] is None or isinstance(r["frame"], int)


def test_object_aware_build_records_its_settings_and_keeps_the_hand_out(tiny, tmp_path):
    """``contact=`` reaches the retargeter with each motion's own object trajectory: in the references it
    keeps, the links off the distal phalanges stay (nearly) out of the object while holding it
    (MuJoCo's collision check), where the keypoint-only build of the same motions sinks them in."""
    contact = ObjectContact()
    report = build_dataset("tiny", tmp_path / "oc", seed=SEED, progress=False, limit=2, contact=contact)
    ds = ReferenceDataset(report.path)
    assert ds.info["object_contact"] == dataclasses.asdict(contact) and tiny[1].info["object_contact"] is None
    blind = {e["name"]: i for i, e in enumerate(tiny[1].entries)}
    deepest = {}
    for i, e in enumerate(ds.entries):
        for name, data in (("aware", ds), ("blind", tiny[1] if e["name"] in blind else None)):
            if data is None:
                continue
            ref = data[i if name == "aware" else blind[e["name"]]]
            hold = slice(ref.meta["phases"]["manipulate"], ref.meta["phases"]["release"])
            depth = hand_object_overlap(ref.hand_joint_pos[hold], ref.object_pose[hold], ref.object_name)
            off_tips = [d.max() for n, d in depth.items() if n not in TIP_GEOMS + PAD_GEOMS]
            deepest.setdefault(name, []).append(max(off_tips))
    # a soft penalty against noisy human keypoints: a few mm remain on some frames (keypoints alone: 2–3 cm)
    assert len(deepest["aware"]) >= 2 and len(deepest["blind"]) >= 2, deepest
    assert max(deepest["aware"]) < 0.008 and max(deepest["aware"]) < 0.5 * min(deepest["blind"]), deepest


def test_splits(tiny):
    _, ds = tiny
    held = set(held_out_objects())
    refs = list(ds)
    seen = {i for i, r in enumerate(refs) if r.object_name not in held}
    unseen = {i for i, r in enumerate(refs) if r.object_name in held}
    assert set(ds.splits) == {"unseen_trajectory", "unseen_object"}
    traj_train, traj_test = set(ds.split("unseen_trajectory", "train")), set(ds.split("unseen_trajectory", "test"))
    obj_train, obj_test = set(ds.split("unseen_object", "train")), set(ds.split("unseen_object", "test"))
    assert not traj_train & traj_test
    assert traj_train | traj_test == seen
    assert obj_test == unseen
    assert not (traj_train | obj_train) & unseen
    assert not obj_train & obj_test
    assert all(refs[i].object_name not in held for i in traj_test)
    # The preset holds one object out; with SEED the build exercises both splits.
    assert traj_train and traj_test and obj_test, f"tiny build with seed {SEED} leaves a split part empty: {ds.splits}"


def test_make_splits_on_a_larger_list():
    """Split logic on many cheap references (the tiny build has only a handful)."""
    q = np.tile(HOME_QPOS, (2, 1))
    objs = ["cube_050", "mug_00", "box_04", "mug_03", "bottle_00"] * 8
    refs = [Reference(hand_joint_pos=q, hand_link_pose=np.tile([0, 0, 0, 1.0, 0, 0, 0], (2, 5, 1)),
                      object_pose=np.tile([0.45, 0, 0.03, 1.0, 0, 0, 0], (2, 1)), object_name=o, instruction="x",
                      group_id=i) for i, o in enumerate(objs)]
    s = make_splits(refs, seed=0)
    held = set(held_out_objects())
    seen = [i for i, o in enumerate(objs) if o not in held]
    assert sorted(s["unseen_trajectory"]["train"] + s["unseen_trajectory"]["test"]) == seen
    assert len(s["unseen_trajectory"]["test"]) == round(0.2 * len(seen))
    assert s["unseen_object"]["test"] == [i for i, o in enumerate(objs) if o in held]
    assert s["unseen_object"]["train"] == s["unseen_trajectory"]["train"]
    assert make_splits(refs, seed=0) == s and make_splits(refs, seed=1) != s
    # a reference's part does not hang on the others: drop two and the rest keep theirs but for at most two
    named = [r.with_name(f"ref_{i:02d}") for i, r in enumerate(refs)]
    full = make_splits(named, seed=0)["unseen_trajectory"]
    kept = [k for k in range(len(named)) if k not in (3, 17)]
    fewer = make_splits([named[k] for k in kept], seed=0)["unseen_trajectory"]
    moved = [k for j, k in enumerate(kept) if (j in fewer["test"]) != (k in full["test"])]
    assert len(moved) <= 2


def test_kinematic_replay_matches_stored_link_poses(tiny):
    _, ds = tiny
    for ref in ds:
        poses = KinematicReplay(ref.object_name).link_poses(ref)
        assert poses.shape == ref.hand_link_pose.shape
        np.testing.assert_allclose(poses[..., :3], ref.hand_link_pose[..., :3], atol=1e-5, rtol=0)
        q, q_ref = poses[..., 3:], ref.hand_link_pose[..., 3:]
        sign = np.where(np.einsum("...i,...i->...", q, q_ref) < 0, -1.0, 1.0)[..., None]
        np.testing.assert_allclose(sign * q, q_ref, atol=1e-4, rtol=0)


def test_same_seed_same_dataset(tiny, tmp_path):
    report, ds = tiny
    again = build_dataset("tiny", tmp_path / "again", seed=SEED, progress=False)
    ds2 = ReferenceDataset(tmp_path / "again")
    assert again.rejections == report.rejections
    assert [e["name"] for e in ds2.entries] == [e["name"] for e in ds.entries]
    assert ds2.splits == ds.splits
    for key in ("hand_joint_pos", "hand_link_pose", "object_pose", "human_keypoints", "retarget_residual"):
        a, b = ds.frames[key].numpy(), ds2.frames[key].numpy()
        assert np.array_equal(a, b, equal_nan=True), key
    assert [e["meta"] for e in ds2.entries] == [e["meta"] for e in ds.entries]


def test_plan_instructions_seeded():
    preset = PRESETS["small"]
    a = plan_instructions(preset, seed=0)
    assert a == plan_instructions(preset, seed=0)
    assert a != plan_instructions(preset, seed=1)
    assert len(a) == preset.base_instructions
    assert {i.object_name for i in a} == set(preset.objects)      # 100 instructions cover all 80 objects
    assert {i.verb for i in a} == set(VERBS)


def test_unknown_preset():
    with pytest.raises(ValueError, match=r"unknown preset 'nope'; choose one of \['paper', 'small', 'tiny'\]"):
        build_dataset("nope", "/nonexistent/never-written")


# ------------------------------------------------------------------------------------------------
# Feasibility


CUBE = "cube_050"
CUBE_REST = np.array([0.45, 0.0, get_object(CUBE).half_height + 1e-3, 1.0, 0.0, 0.0, 0.0])
T_REF, BAD_FROM = 320, 150


def reference(q_bad: np.ndarray | None = None, T: int = T_REF) -> Reference:
    """HOME_QPOS (palm ~0.33 m from the cube, so the episode window starts at frame 0), switching to
    ``q_bad`` from frame BAD_FROM on."""
    q = np.tile(HOME_QPOS, (T, 1))
    if q_bad is not None:
        q[BAD_FROM:] = q_bad
    return Reference.from_joint_positions(q, np.tile(CUBE_REST, (T, 1)), object_name=CUBE, instruction="test",
                                          group_id=0, name="test")


def with_joints(**values) -> np.ndarray:
    q = HOME_QPOS.copy()
    for name, v in values.items():
        q[JOINT_NAMES.index(name)] = v
    return q


def test_feasible_reference_passes():
    ref = reference()
    assert ref.window() == slice(0, WINDOW_FRAMES)
    assert check(ref) is None
    assert check(ref, retarget_palm_error=np.full(T_REF, 0.01), retarget_tip_error=np.full(T_REF, 0.03)) is None


def test_arm_into_table_is_rejected():
    q_bad = with_joints(arm_j2=0.7, arm_j3=-0.9)
    ref = reference(q_bad)
    poses = KinematicReplay(CUBE).link_poses(ref)
    assert poses[:BAD_FROM, :, 2].min() > 0.1                # the hand is well above the table first …
    assert poses[BAD_FROM:, :, 2].min() < 0.0                # … then below the table top
    rej = check(ref)
    assert isinstance(rej, Rejection) and rej.reason == "table_collision" and rej.frame == BAD_FROM
    assert "table" in rej.detail and f"frame {BAD_FROM}" in rej.detail
    assert rej.as_dict() == {"reason": "table_collision", "frame": BAD_FROM, "detail": rej.detail}


def test_hand_folded_onto_the_arm_is_rejected():
    """The wrist (arm_j5) bent all the way back folds the fingers onto the upper arm, high above the table."""
    q_bad = with_joints(arm_j5=3.1)
    ref = reference(q_bad)
    poses = KinematicReplay(CUBE).link_poses(ref)
    assert poses[BAD_FROM:, :, 2].min() > 0.3                # nowhere near the table
    rej = check(ref)
    assert rej is not None and rej.reason == "hand_arm_collision" and rej.frame == BAD_FROM, rej
    assert "link" in rej.detail and "_col" in rej.detail     # names the arm link and the finger geom
    # A milder bend of the same joint is fine.
    assert check(reference(with_joints(arm_j5=0.9))) is None


def test_large_retarget_errors_are_unreachable():
    ref = reference()
    palm = np.full(T_REF, 0.01)
    palm[[40, 90]] = 0.06
    rej = check(ref, retarget_palm_error=palm)
    assert rej.reason == "unreachable" and rej.frame == 40 and "6.0 cm" in rej.detail and "wrist/palm" in rej.detail
    tips = np.full(T_REF, 0.02)
    tips[77:] = 0.2
    rej = check(ref, retarget_palm_error=np.full(T_REF, 0.01), retarget_tip_error=tips)
    assert rej.reason == "unreachable" and rej.frame == 77 and "fingertips" in rej.detail
    # Unreachable is reported before collisions.
    rej = check(reference(with_joints(arm_j2=0.7, arm_j3=-0.9)), retarget_palm_error=palm)
    assert rej.reason == "unreachable"


def test_short_reference_is_rejected():
    rej = check(reference(T=WINDOW_FRAMES - 10))
    assert rej.reason == "window_too_short" and rej.frame is None
    assert "missing" in rej.detail


def test_reasons_are_the_documented_ones():
    assert set(REASONS) == {"no_grasp", "no_planned_grasp", "two_hands", "unreachable", "hand_arm_collision",
                            "table_collision", "window_too_short"}


def test_dataset_at_uses_builds_or_refuses(tiny, tmp_path):
    """The recipes' one build-if-missing: a dataset is used as it is, a missing folder is built into, a
    folder of other files is refused untouched, and nothing is built without a preset."""
    from adadex.data.build import dataset_at

    _, ds = tiny
    said = []
    assert dataset_at(ds.path, preset="tiny", setting="dataset", log=said.append) == ds.path and said == []
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("x")
    with pytest.raises(FileNotFoundError, match=r"dataset=.*mine: not a reference dataset .*not empty"):
        dataset_at(mine, preset="tiny", setting="dataset")
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    with pytest.raises(FileNotFoundError, match=r"data_dir=.*nothing: no reference dataset there \(set it\)"):
        dataset_at(tmp_path / "nothing", preset=None, setting="data_dir", hint="set it")
    assert not (tmp_path / "nothing").exists()
    built = dataset_at(tmp_path / "built", preset="tiny", setting="dataset", seed=SEED, progress=False,
                       log=said.append)
    assert said == [f"building the tiny reference dataset into {tmp_path / 'built'}"]
    assert [e["name"] for e in ReferenceDataset(built).entries] == [e["name"] for e in ds.entries]


def test_dataset_at_says_when_a_planned_grasp_was_made_by_an_earlier_planner(tiny, tmp_path):
    """A build's info records its grasp planner; one made by an earlier planner is still used (a user may
    compare against it on purpose), but the recipe says its references are not today's."""
    from adadex.data.build import dataset_at
    from adadex.data.planned_grasp import PLANNER_VERSION
    from adadex.data.reference import save_dataset

    _, ds = tiny
    refs = [ds[i] for i in range(len(ds))]
    for version, noted in ((None, True), (PLANNER_VERSION - 1, True), (PLANNER_VERSION, False)):
        info = {"planned_grasp": True, **({} if version is None else {"planner": version})}
        path = save_dataset(refs, tmp_path / f"v{version}", splits=ds.splits, info=info)
        said = []
        assert dataset_at(path, preset="tiny", setting="dataset", log=said.append) == path
        assert bool(said) == noted
        if noted:
            assert f"grasp planner {version or 1}, not today's {PLANNER_VERSION}" in said[0]
    said = []
    dataset_at(ds.path, preset="tiny", setting="dataset", log=said.append)      # no planned grasp: nothing to say
    assert said == []
