"""`refine` takes the keypoints as the rest of earcore.pose describes them: the names
of the dataset's manifest, the ONNX sidecar and `PoseEstimate.keypoint_names` (the last
one "flange": for the iiwa 45 mm along link 7's z, `earcore.robots.FLANGES`), or their
frames ([link name, [x, y, z]], the manifest's and the sidecar's `keypoint_frames`);
`refine_predictions` recovers noiseless keypoints through the manifest's frames;
degenerate inputs (intrinsics that are not 3x3, a link index out of range) are
ValueErrors that say so."""

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


def test_refine_takes_the_manifests_keypoint_frames(ur5):
    frames = [[link, [0.0, 0.0, 0.0]] for link in _links(ur5)] + [["forearm_link", [0.0, 0.0, 0.1]]]  # and 10 cm along the forearm's z
    forearm = ur5.fk(Q)[ur5.link_names.index("forearm_link")] @ [0.0, 0.0, 0.1, 1.0]
    points = np.vstack([_points(ur5), forearm[:3] + [0.1, 0.2, 2.0]])
    fit = refine(ur5, points, frames=frames)
    assert np.abs(fit.keypoints - points).max() < 1e-4


def _links(ur5):
    return [ur5.link_names[i] for i in keypoint_links(ur5, UR_NAMES[:-1] + ["tool0"])]


def test_an_unknown_link_in_the_frames_is_named(ur5):
    with pytest.raises(ValueError, match="'gripper' is not a link of ur5"):
        refine(ur5, _points(ur5), frames=[["gripper", [0, 0, 0]]] * 7)


def test_refine_predictions_recovers_noiseless_keypoints_through_the_manifests_frames(ur5):
    """A robot model's keypoints (the generator's definition, forward kinematics) seen
    by a camera, given to `refine_predictions` as a network's pixels and depths: the fit
    through the manifest's `keypoint_frames` gives them back."""
    pytest.importorskip("pybullet")
    from earcore.pose.evaluate import refine_predictions
    from earcore.sim.robot_images import RobotImageOptions, keypoint_frames, keypoint_positions, manifest_for

    frames = manifest_for(RobotImageOptions(robots=("ur5",)), [])["keypoint_frames"]
    assert frames["ur5"][-1][0] == "tool0"
    k = np.array([[110.0, 0.0, 63.5], [0.0, 110.0, 52.5], [0.0, 0.0, 1.0]])
    r = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])  # looking along the world's -x, z up in the image
    t = -r @ np.array([2.2, 0.1, 0.5])
    world = keypoint_positions(ur5, keypoint_frames(ur5, "ur5"), Q)
    cam = world @ r.T + t
    base = r @ np.asarray(ur5.base)[:3, 3] + t
    points = np.vstack([cam, base])
    pixels = np.stack([k[0, 0] * points[:, 0] / points[:, 2] + k[0, 2], k[1, 1] * points[:, 1] / points[:, 2] + k[1, 2]], 1)
    p = {
        "keypoints": cam[None].astype(np.float32),
        "pixels": pixels[None].astype(np.float32),
        "base": base[None].astype(np.float32),
        "intrinsics": k[None].astype(np.float32),
        "robot": np.array([0]),
        "type": np.array([0]),
    }
    out = refine_predictions(p, ["ur5"], frames)
    assert np.abs(out["keypoints"][0] - cam).max() < 1e-3
    assert np.abs(out["base"][0] - base).max() < 1e-3
    # With the joint angles known (the labels'), PnP on the same pixels gives them back too.
    p["joints"] = np.asarray(Q, dtype=np.float32)[None]
    out = refine_predictions(p, ["ur5"], frames, mode="pnp")
    assert np.abs(out["keypoints"][0] - cam).max() < 1e-3
    assert np.abs(out["base"][0] - base).max() < 1e-3
    with pytest.raises(ValueError, match="mode must be one of fit, pnp"):
        refine_predictions(p, ["ur5"], frames, mode="icp")
