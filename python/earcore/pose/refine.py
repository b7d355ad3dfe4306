"""Kinematic refinement: the joint angles and the base pose that best explain a
network's keypoints, through the robot's forward kinematics and Jacobians (earcore's
core, imported when called), and PnP for the base when the joint angles are known
(as DREAM does).

`refine` minimises, by Levenberg-Marquardt in numpy, over q (within the joint limits)
and camera_from_base (R, t):

    Σ_k ‖π(R·b_k(q) + t) - uv_k‖² / σ_px²  +  (z_k - ẑ_k)² / σ_z²      (pixels given)
    Σ_k ‖R·b_k(q) + t - p_k‖² / σ_3d²                                 (3D only)

where b_k(q) is keypoint k in the base frame (a link origin, or a point fixed to a
link), and the base itself (the base frame's origin) is one more observation. With
pixels, the robot's known link lengths fix the scale the network's depth gets wrong;
the depth term, loosely weighted, only picks the right solution. Each observation's term
(its pixel and depth residuals together) goes through Cauchy's ρ(r²) = c² log(1 + r²/c²)
(`robust` = c, 3 σ by default; None: least squares), so one misplaced keypoint does not
drag the others. Several starts (the
joint-range midpoint, then random configurations) guard against local minima.

What keypoints cannot show stays at its start: a joint whose rotation moves no
keypoint (a UR's last joint turns tool0 about its own axis), and the split between
the first joint and the base's rotation about it. Without the base observation, the
base's tilt about the first keypoint also trades against the shoulder angle (the
keypoints still fit; the angles do not): pass the network's base.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from earcore.pose.errors import PoseError

__all__ = ["Frames", "RefineResult", "keypoint_links", "keypoints_in_base", "pnp_base", "refine", "resolve_keypoints"]


@dataclass
class RefineResult:
    joints: np.ndarray  # (dof,)
    camera_from_base: np.ndarray  # (4, 4)
    keypoints: np.ndarray  # (K, 3) the fitted keypoints, camera frame
    base: np.ndarray  # (3,)
    cost: float  # the final weighted sum of squares per residual
    iterations: int


#: Where keypoints sit: [link name, [x, y, z]] pairs (the offset in that link's frame,
#: m), as the dataset manifest's and the ONNX sidecar's `keypoint_frames` give them.
Frames = Sequence[Sequence[Any]]


def resolve_keypoints(robot: Any, names: Sequence[str] | None = None, frames: Frames | None = None) -> tuple[list[int], np.ndarray]:
    """Each keypoint's link index and offset (K, 3) in that link's frame, from `frames`
    (the manifest's or the sidecar's `keypoint_frames[robot]`) or from `names`: a link
    (its origin), an actuated joint (its frame's origin, `keypoint_links`) or "flange"
    (the robot's flange, `earcore.robots.FLANGES`: for the iiwa 45 mm along link 7)."""
    links = list(robot.link_names)
    if frames is not None:
        out, offsets = [], []
        for i, frame in enumerate(frames):
            try:
                link, offset = frame
                xyz = np.asarray(offset, dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"keypoint frame {i} must be [link name, [x, y, z]], got {frame!r}") from None
            if link not in links:
                raise ValueError(f"keypoint frame {i}: {link!r} is not a link of {robot.name}")
            if xyz.shape != (3,) or not np.isfinite(xyz).all():
                raise ValueError(f"keypoint frame {i}: the offset must be 3 finite numbers, got {offset!r}")
            out.append(links.index(link))
            offsets.append(xyz)
        return out, np.array(offsets, dtype=np.float64).reshape(len(out), 3)
    if names is None:
        raise ValueError("give the keypoints' links, frames or names")
    from earcore.robots import FLANGES

    flange = FLANGES.get(str(robot.name).lower())
    out, offsets = [], []
    for name in names:
        if name == "flange" and name not in links:
            if flange is None:
                raise ValueError(f"{robot.name} has no known flange: give the keypoints' frames ([link name, [x, y, z]] pairs)")
            out.append(links.index(flange[0]))
            offsets.append(np.array(flange[1], dtype=np.float64))
        else:
            out += keypoint_links(robot, [name])
            offsets.append(np.zeros(3))
    return out, np.array(offsets, dtype=np.float64).reshape(len(out), 3)


def _check_links(robot: Any, links: Sequence[int]) -> list[int]:
    n = len(robot.link_names)
    out = []
    for link in links:
        if isinstance(link, (bool, np.bool_)) or not isinstance(link, (int, np.integer)) or not 0 <= int(link) < n:
            raise ValueError(f"link index {link!r} is not one of {robot.name}'s {n} links (0 to {n - 1})")
        out.append(int(link))
    return out


def _check_intrinsics(intrinsics: Any) -> np.ndarray:
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (3, 3) or not np.isfinite(k).all():
        raise ValueError(f"intrinsics must be a finite 3x3 matrix, got shape {k.shape}")
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise ValueError(f"intrinsics: the focal lengths must be > 0, got fx {k[0, 0]}, fy {k[1, 1]}")
    return k


def _keypoint_frames(
    robot: Any, count: int | None, links: Sequence[int] | None, names: Sequence[str] | None, frames: Frames | None, offsets: np.ndarray | None
) -> tuple[list[int], np.ndarray | None]:
    """The checked links and offsets of refine's and pnp_base's keypoint arguments."""
    if links is None:
        links, found = resolve_keypoints(robot, names, frames)
        offsets = found if offsets is None else offsets
    links = _check_links(robot, links)
    if count is not None and len(links) != count:
        raise ValueError(f"{count} keypoints but {len(links)} links")
    if offsets is not None:
        offsets = np.asarray(offsets, dtype=np.float64)
        if offsets.shape != (len(links), 3) or not np.isfinite(offsets).all():
            raise ValueError(f"offsets must be finite (K, 3) = ({len(links)}, 3), got {offsets.shape}")
    return links, offsets


def keypoint_links(robot: Any, names: Sequence[str]) -> list[int]:
    """Link indices of keypoints named by link (origin of that link) or by joint (the
    origin of its frame = its child link's origin)."""
    links = list(robot.link_names)
    joints = list(robot.joint_names)
    children = _joint_children(robot)
    out = []
    for name in names:
        if name in links:
            out.append(links.index(name))
        elif name in joints:
            out.append(children[joints.index(name)])
        else:
            raise ValueError(f"keypoint {name!r} is neither a link nor an actuated joint of {robot.name} (the flange: `resolve_keypoints`)")
    return out


def _joint_children(robot: Any) -> list[int]:
    """Each actuated joint's child link: of the links it moves, the one moved by the fewest
    joints, first in the root-first link order."""
    q = _start(robot)
    moved = []
    for link in range(len(robot.link_names)):
        w = np.abs(robot.frame_jacobian(q, link)[3:]).sum(0) > 1e-12
        moved.append(w)
    out = []
    for j in range(robot.dof):
        candidates = [(int(m.sum()), link) for link, m in enumerate(moved) if m[j]]
        out.append(min(candidates)[1] if candidates else 0)
    return out


def _limits(robot: Any) -> tuple[np.ndarray, np.ndarray]:
    lim = np.clip(np.asarray(robot.joint_limits, dtype=np.float64), -np.pi, np.pi)
    margin = 1e-9 * np.maximum(1.0, np.abs(lim))
    return lim[:, 0] + margin[:, 0], lim[:, 1] - margin[:, 1]


def _start(robot: Any) -> np.ndarray:
    lo, hi = _limits(robot)
    return 0.5 * (lo + hi)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _exp(w: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(w))
    k = _skew(w)
    if theta < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(theta) / theta * k + (1 - np.cos(theta)) / theta**2 * (k @ k)


def _kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t with R·a + t ≈ b."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


class _Chain:
    """Keypoints in the base frame and their Jacobians for the chosen links (and offsets)."""

    def __init__(self, robot: Any, links: Sequence[int], offsets: np.ndarray | None):
        self.robot, self.links = robot, list(links)
        self.offsets = np.zeros((len(self.links), 3)) if offsets is None else np.asarray(offsets, dtype=np.float64).reshape(len(self.links), 3)
        base = np.asarray(robot.base, dtype=np.float64)
        self.base_inv = np.linalg.inv(base)

    def points(self, q: np.ndarray) -> np.ndarray:
        frames = self.base_inv @ self.robot.fk(q)
        return np.array([frames[link, :3, :3] @ off + frames[link, :3, 3] for link, off in zip(self.links, self.offsets)])

    def jacobians(self, q: np.ndarray) -> np.ndarray:
        frames = self.robot.fk(q)
        rot = self.base_inv[:3, :3]
        out = []
        for link, off in zip(self.links, self.offsets):
            world = frames[link, :3, :3] @ off + frames[link, :3, 3]
            out.append(rot @ self.robot.jacobian(q, link, world))
        return np.array(out)  # (K, 3, dof)


def keypoints_in_base(robot: Any, joints: np.ndarray, *, frames: Frames | None = None, names: Sequence[str] | None = None) -> np.ndarray:
    """The keypoints (K, 3) in the robot's base frame at `joints`, given as for `refine`."""
    links, offsets = _keypoint_frames(robot, None, None, names, frames, None)
    return _Chain(robot, links, offsets).points(np.asarray(joints, dtype=np.float64))


def refine(
    robot: Any,
    keypoints: np.ndarray,
    *,
    links: Sequence[int] | None = None,
    names: Sequence[str] | None = None,
    frames: Frames | None = None,
    offsets: np.ndarray | None = None,
    base: np.ndarray | None = None,
    pixels: np.ndarray | None = None,
    base_pixel: np.ndarray | None = None,
    intrinsics: np.ndarray | None = None,
    sigma_px: float = 2.0,
    sigma_z: float = 0.15,
    sigma_3d: float = 0.03,
    starts: int = 6,
    iterations: int = 60,
    seed: int = 0,
    robust: float | None = 3.0,
) -> RefineResult:
    """Fit `robot` (an `earcore.robots.RobotModel`, or a name such as "ur5") to keypoints
    (K, 3) in the camera frame. Keypoints are `links` (indices, optionally at `offsets`
    (K, 3) in their link frames), `frames` ([link name, [x, y, z]] pairs: the dataset
    manifest's or the ONNX sidecar's `keypoint_frames[robot]`, `PoseEstimate.keypoint_frames`)
    or `names` (links, joints or "flange": `PoseEstimate.keypoint_names`; see
    `resolve_keypoints`). With `pixels` (K, 2) and `intrinsics` (3, 3) the fit is in the
    image (see the module doc); `base` (3,) and `base_pixel` (2,) add the base as an
    observation."""
    if isinstance(robot, str):
        from earcore import robots as _robots

        robot = _robots.load(robot)
    p3 = np.asarray(keypoints, dtype=np.float64)
    if p3.ndim != 2 or p3.shape[1] != 3 or not np.isfinite(p3).all():
        raise ValueError(f"keypoints must be finite (K, 3), got shape {p3.shape}")
    links, offsets = _keypoint_frames(robot, len(p3), links, names, frames, offsets)
    use_pixels = pixels is not None
    if use_pixels:
        if intrinsics is None:
            raise ValueError("pixels need the intrinsics")
        k = _check_intrinsics(intrinsics)
        uv = np.asarray(pixels, dtype=np.float64)
        if uv.shape != (len(p3), 2) or not np.isfinite(uv).all():
            raise ValueError(f"pixels must be finite (K, 2) = ({len(p3)}, 2), got {uv.shape}")
    chain = _Chain(robot, links, offsets)
    lo, hi = _limits(robot)
    dof = robot.dof

    # Observations: the keypoints, then (if given) the base = the base frame's origin.
    obs3 = p3 if base is None else np.vstack([p3, np.asarray(base, dtype=np.float64).reshape(1, 3)])
    obs_uv = None
    if use_pixels:
        obs_uv = uv
        if base is not None:
            bp = base_pixel if base_pixel is not None else (k @ obs3[-1])[:2] / obs3[-1, 2]
            obs_uv = np.vstack([uv, np.asarray(bp, dtype=np.float64).reshape(1, 2)])

    def model_points(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = chain.points(q)
        jb = chain.jacobians(q)
        if base is not None:
            b = np.vstack([b, np.zeros((1, 3))])
            jb = np.concatenate([jb, np.zeros((1, 3, dof))])
        return b, jb

    def residuals(q: np.ndarray, r: np.ndarray, t: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        b, jb = model_points(q)
        p = b @ r.T + t
        n = len(p)
        if obs_uv is None:
            res = ((p - obs3) / sigma_3d).ravel()
        else:
            z = np.maximum(p[:, 2], 1e-3)
            u = k[0, 0] * p[:, 0] / z + k[0, 2]
            v = k[1, 1] * p[:, 1] / z + k[1, 2]
            res = np.concatenate([np.stack([u - obs_uv[:, 0], v - obs_uv[:, 1]], 1) / sigma_px, ((p[:, 2] - obs3[:, 2]) / sigma_z)[:, None]], 1).ravel()
        if not jac:
            return res, None
        # d p / d (q, ω, t): R·J_b(q); -[R·b]× (R ← exp(ω)·R); I
        dp = np.zeros((n, 3, dof + 6))
        dp[:, :, :dof] = np.einsum("ij,kjd->kid", r, jb)
        dp[:, :, dof : dof + 3] = -np.array([_skew(v) for v in (b @ r.T)])
        dp[:, :, dof + 3 :] = np.eye(3)
        if obs_uv is None:
            return res, (dp / sigma_3d).reshape(n * 3, dof + 6)
        proj = np.zeros((n, 3, 3))
        proj[:, 0, 0] = k[0, 0] / z / sigma_px
        proj[:, 0, 2] = -k[0, 0] * p[:, 0] / z**2 / sigma_px
        proj[:, 1, 1] = k[1, 1] / z / sigma_px
        proj[:, 1, 2] = -k[1, 1] * p[:, 1] / z**2 / sigma_px
        proj[:, 2, 2] = 1.0 / sigma_z
        return res, np.einsum("kab,kbd->kad", proj, dp).reshape(n * 3, dof + 6)

    # A network's keypoints fail by whole joints (an occluded wrist put elsewhere), not
    # by Gaussian noise: with `robust`, each observation's residual (in σ units) costs
    # Cauchy's c² log(1 + r²/c²), minimised by reweighted Gauss-Newton steps.
    def total(res: np.ndarray) -> float:
        if robust is None:
            return float(res @ res)
        r2 = (res.reshape(-1, 3) ** 2).sum(1)
        return float((robust**2 * np.log1p(r2 / robust**2)).sum())

    def reweighted(res: np.ndarray, jmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if robust is None:
            return res, jmat
        r2 = (res.reshape(-1, 3) ** 2).sum(1)
        w = np.repeat(1.0 / np.sqrt(1.0 + r2 / robust**2), 3)
        return res * w, jmat * w[:, None]

    def solve(q: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, int]:
        b, _ = model_points(q)
        r, t = _kabsch(b, obs3)
        res, jmat = residuals(q, r, t, True)
        cost = total(res)
        lam = 1e-3
        it = 0
        for it in range(1, iterations + 1):  # noqa: B007 (the count is reported)
            assert jmat is not None
            wres, wjac = reweighted(res, jmat)
            a = wjac.T @ wjac
            g = wjac.T @ wres
            step = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-9), -g)
            q_new = np.clip(q + step[:dof], lo, hi)
            r_new = _exp(step[dof : dof + 3]) @ r
            t_new = t + step[dof + 3 :]
            res_new, _ = residuals(q_new, r_new, t_new, False)
            cost_new = total(res_new)
            if cost_new < cost:
                improvement = cost - cost_new
                q, r, t, cost = q_new, r_new, t_new, cost_new
                res, jmat = residuals(q, r, t, True)
                lam = max(lam / 3, 1e-9)
                if improvement < 1e-10 * (1 + cost) or np.linalg.norm(step) < 1e-10:
                    break
            else:
                lam *= 4
                if lam > 1e8:
                    break
        return cost, q, r, t, it

    rng = np.random.default_rng(seed)
    tries = [_start(robot)] + [rng.uniform(lo, hi) for _ in range(max(0, starts - 1))]
    best = None
    for q0 in tries:
        found = solve(q0)
        if best is None or found[0] < best[0]:
            best = found
    if best is None:
        raise PoseError("the refinement had no start")
    cost, q, r, t, it = best
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = r, t
    fitted = chain.points(q) @ r.T + t
    return RefineResult(joints=q, camera_from_base=pose, keypoints=fitted, base=t.copy(), cost=cost / max(1, len(obs3) * 3), iterations=it)


def pnp_base(
    robot: Any,
    joints: np.ndarray,
    pixels: np.ndarray,
    intrinsics: np.ndarray,
    *,
    links: Sequence[int] | None = None,
    names: Sequence[str] | None = None,
    frames: Frames | None = None,
    offsets: np.ndarray | None = None,
    base_pixel: np.ndarray | None = None,
    outlier_px: float | None = None,
) -> np.ndarray:
    """camera_from_base (4, 4) from the keypoints' pixels (K, 2) when the joint angles are
    known: their base-frame positions by forward kinematics, then OpenCV's solvePnP
    (EPnP, refined iteratively). `base_pixel` (2,) adds the base frame's origin as one
    more point. With `outlier_px`, points farther than that from their reprojection
    under a RANSAC consensus (at least 4 of them) are left out before the refinement (a
    network's keypoints fail by whole joints). Needs at least 4 points; the keypoints are
    given as for `refine`."""
    try:
        import cv2
    except ImportError as exc:
        raise ImportError("PnP needs OpenCV: pip install opencv-python-headless") from exc
    if isinstance(robot, str):
        from earcore import robots as _robots

        robot = _robots.load(robot)
    links, offsets = _keypoint_frames(robot, None, links, names, frames, offsets)
    uv = np.asarray(pixels, dtype=np.float64)
    if uv.shape != (len(links), 2) or not np.isfinite(uv).all():
        raise ValueError(f"pixels must be finite (K, 2) = ({len(links)}, 2), got {uv.shape}")
    if len(links) < 4:
        raise ValueError(f"PnP needs at least 4 keypoints, got {len(links)}")
    obj = _Chain(robot, links, offsets).points(np.asarray(joints, dtype=np.float64))
    if base_pixel is not None:
        bp = np.asarray(base_pixel, dtype=np.float64).reshape(-1)
        if bp.shape != (2,) or not np.isfinite(bp).all():
            raise ValueError(f"base_pixel must be 2 finite numbers, got {base_pixel!r}")
        obj, uv = np.vstack([obj, np.zeros((1, 3))]), np.vstack([uv, bp[None]])
    k = _check_intrinsics(intrinsics)
    if outlier_px is not None:
        if not outlier_px > 0:
            raise ValueError(f"outlier_px must be > 0, got {outlier_px!r}")
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(obj, uv, k, None, reprojectionError=float(outlier_px), iterationsCount=200, flags=cv2.SOLVEPNP_EPNP)
        if ok and inliers is not None and len(inliers) >= 4:
            keep = inliers.ravel()
            obj, uv = obj[keep], uv[keep]
    ok, rvec, tvec = cv2.solvePnP(obj, uv, k, None, flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        raise PoseError("PnP found no pose")
    ok, rvec, tvec = cv2.solvePnP(obj, uv, k, None, rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise PoseError("PnP's refinement failed")
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rvec)[0]
    pose[:3, 3] = tvec.ravel()
    return pose
