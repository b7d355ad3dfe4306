"""Review: `refine` cannot take the keypoints the rest of earcore.pose names.

The dataset's manifest, the ONNX sidecar and `PoseEstimate.keypoint_names` call the last
keypoint "flange" (for the iiwa: 45 mm along link 7's z, `FLANGES`); `refine` and
`pnp_base` accept only link or joint names, so `refine(robot, est.keypoints,
names=est.keypoint_names)` fails with "keypoint 'flange' is neither a link nor an
actuated joint", and a user who guesses the link ("lbr_iiwa_link_7") fits the iiwa with
a keypoint 45 mm off. Degenerate inputs end in numpy's IndexError."""

from __future__ import annotations

import numpy as np
import pytest

robots = pytest.importorskip("earcore.robots")

from earcore.pose.refine import keypoint_links, refine  # noqa: E402

#: what the dataset's manifest and the sidecar list for a UR (docs/robot-images.md)
UR_NAMES = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint", "flange"]
Q = np.array([0.4, -1.1, 1.3, -0.9, 1.2, 0.3])


@pytest.fixture(scope="module")
def ur5():
    try:
        return robots.load("ur5")
    except ImportError as exc:
        pytest.skip(str(exc))


def _points(ur5):
    links = keypoint_links(ur5, UR_NAMES[:-1] + ["tool0"])
    return ur5.fk(Q)[links, :3, 3] + np.array([0.1, 0.2, 2.0])


def test_refine_takes_the_datasets_keypoint_names(ur5):
    points = _points(ur5)
    fit = refine(ur5, points, names=UR_NAMES)
    assert np.abs(fit.keypoints - points).max() < 1e-5


def test_refine_takes_the_iiwa_flange_at_its_offset():
    try:
        iiwa = robots.load("iiwa")
    except ImportError as exc:
        pytest.skip(str(exc))
    names = [n for n in iiwa.joint_names][:7] + ["flange"]
    q = np.array([0.3, 0.5, -0.2, -1.2, 0.4, 0.8, 0.1])
    frames = iiwa.fk(q)
    links = keypoint_links(iiwa, names[:-1])
    tip = frames[iiwa.link_names.index("lbr_iiwa_link_7")] @ [0, 0, 0.045, 1]  # the generator's flange
    points = np.vstack([frames[links, :3, 3], tip[:3]]) + [0.0, 0.0, 2.0]
    fit = refine(iiwa, points, names=names)
    assert np.abs(fit.keypoints - points).max() < 1e-4


@pytest.mark.parametrize(
    "label,kwargs",
    [
        ("intrinsics 2x2", {"pixels": np.zeros((7, 2)), "intrinsics": np.eye(2)}),
        ("a link index out of range", {"links": [1, 2, 3, 4, 5, 6, 99]}),
    ],
)
def test_degenerate_input_is_a_clear_value_error(ur5, label, kwargs):
    args = {"keypoints": _points(ur5), "links": keypoint_links(ur5, UR_NAMES[:-1] + ["tool0"]), **kwargs}
    with pytest.raises(ValueError):
        refine(ur5, **args)
