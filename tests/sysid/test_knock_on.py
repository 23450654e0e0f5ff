"""A joint moved exactly as measured (:meth:`~adadex.sysid.replay.Replayer.simulate_imposed`): the test the
diagnosis uses to tell a knock-on from a source (:func:`~adadex.sysid.joint_selection._follows`), on the tiny arm of
:mod:`tests.sysid.user_model` with effects hidden by ``MjSpec`` edits (as in test_user_model_diagnosis.py)."""

import numpy as np
import pytest

from adadex.sysid.compare import FAIL_ABS, noise_floor
from adadex.sysid.replay import Replayer
from tests.sysid.test_user_model_diagnosis import SHOULDER_LIMIT, cubic_drag, torque_limit
from tests.sysid.user_model import arm_recording, edited_arm, write_tiny_arm


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    return write_tiny_arm(tmp_path_factory.mktemp("model"))


def _rms(sim, rec) -> np.ndarray:
    return np.sqrt(np.mean((sim - rec.joint_pos) ** 2, axis=(0, 1)))


def test_an_imposed_joint_moves_as_measured_and_takes_a_missing_effect_with_it(arm):
    """A drag on the elbow the model lacks moves the holding shoulder by 2.3 mrad (a knock-on: it fails).
    With the elbow imposed, the elbow is on its measurement to 1e-6 rad and the shoulder's error falls to
    its noise, on the nominal model as on the true one: the shoulder feels the elbow's measured motion,
    whatever torque made it."""
    truth = edited_arm(arm, cubic_drag("elbow", 0.5), "dragged_elbow")
    rec = arm_recording(arm, truth, ["elbow"], seed=1)
    noise = noise_floor(rec.joint_pos)
    free = _rms(Replayer(rec, nthread=1).simulate(), rec)
    assert free[0] > FAIL_ABS and free[0] > 3 * noise[0]          # the shoulder fails as a knock-on
    for model in (None, truth):
        imposed = _rms(Replayer(rec, nthread=1, model=model).simulate_imposed(imposed=["elbow"]), rec)
        assert imposed[1] < 1e-6, imposed
        assert imposed[0] < 1.5 * noise[0], (imposed, noise)
        assert imposed[2] < 1.5 * noise[2], (imposed, noise)


def test_a_source_still_fails_with_its_knock_on_imposed_and_its_knock_on_does_not(arm):
    """A torque-limited shoulder and the elbow it shakes: with the elbow moving as measured the shoulder
    still gives way where the model holds (it is the source); with the shoulder moving as measured the
    elbow is reproduced (its knock-on)."""
    truth = edited_arm(arm, torque_limit("shoulder", SHOULDER_LIMIT), "shoulder_limited")
    rec = arm_recording(arm, truth, ["shoulder", "elbow"], seed=1)
    noise = noise_floor(rec.joint_pos)
    rep = Replayer(rec, nthread=1)
    free = _rms(rep.simulate(), rec)
    assert free[1] > FAIL_ABS and free[1] > 3 * noise[1]
    shoulder = _rms(rep.simulate_imposed(imposed=["elbow"]), rec)[0]
    elbow = _rms(rep.simulate_imposed(imposed=["shoulder"]), rec)[1]
    assert shoulder > 0.5 * free[0], (shoulder, free)
    assert elbow < 3 * noise[1] and elbow < FAIL_ABS, (elbow, noise)
