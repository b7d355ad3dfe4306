"""Robot models: kinematics and padded link bodies (capsules or cylinders), built from URDF.

>>> import earcore
>>> ur5 = earcore.robots.load("ur5")            # doctest: +SKIP
>>> ur5.fk([0, -1.57, 1.57, 0, 0, 0]).shape     # doctest: +SKIP
(11, 4, 4)

Built-in models: ``ur3``, ``ur5``, ``ur10`` (URDFs from the ``example-robot-data``
package) and ``iiwa``, ``panda`` (from ``pybullet_data``); install them with
``pip install 'earcore[robots]'``. Python reads the URDF and meshes; the chain, the
capsules and every query live in Rust (:class:`earcore._earcore.RobotModel`).
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path
from typing import Literal, cast

import numpy as np

from earcore import _earcore
from earcore.urdf import UrdfError, parse_urdf

#: The joint kinds the core models (URDF's names).
JointKind = Literal["revolute", "continuous", "prismatic", "fixed"]

__all__ = ["BUILTIN_MODELS", "FLANGES", "RobotModel", "UrdfError", "load", "urdf_path"]

#: name → (package providing it, path inside the package's data folder)
BUILTIN_MODELS: dict[str, tuple[str, str]] = {
    "ur3": ("example-robot-data", "robots/ur_description/urdf/ur3_robot.urdf"),
    "ur5": ("example-robot-data", "robots/ur_description/urdf/ur5_robot.urdf"),
    "ur10": ("example-robot-data", "robots/ur_description/urdf/ur10_robot.urdf"),
    "iiwa": ("pybullet", "kuka_iiwa/model.urdf"),
    "panda": ("pybullet", "franka_panda/panda.urdf"),
}

#: Each built-in robot's flange (the keypoint "flange" of the pose datasets and
#: networks): (link, offset in that link's frame, m). The iiwa model has no flange link:
#: its flange face is 45 mm along link 7's z (the mesh's end).
FLANGES: dict[str, tuple[str, tuple[float, float, float]]] = {
    "ur3": ("tool0", (0.0, 0.0, 0.0)),
    "ur5": ("tool0", (0.0, 0.0, 0.0)),
    "ur10": ("tool0", (0.0, 0.0, 0.0)),
    "iiwa": ("lbr_iiwa_link_7", (0.0, 0.0, 0.045)),
    "panda": ("panda_link8", (0.0, 0.0, 0.0)),
}

_INSTALL_HINT = "install the robot models with: pip install 'earcore[robots]'"


def _data_folder(package: str) -> Path:
    if package == "pybullet":
        try:
            import pybullet_data
        except ImportError as exc:
            raise ImportError(f"the pybullet package is missing: {_INSTALL_HINT}") from exc
        return Path(pybullet_data.getDataPath())
    try:
        dist = importlib.metadata.distribution(package)
    except importlib.metadata.PackageNotFoundError as exc:
        raise ImportError(f"the {package} package is missing: {_INSTALL_HINT}") from exc
    # example-robot-data installs its data under cmeel.prefix/share/<name>.
    return Path(str(dist.locate_file(f"cmeel.prefix/share/{package}")))


def urdf_path(name: str) -> Path:
    """Path of a built-in model's URDF (``ur3``, ``ur5``, ``ur10``, ``iiwa``, ``panda``)."""
    key = name.lower()
    if key not in BUILTIN_MODELS:
        raise ValueError(f"unknown robot {name!r}; built-in models: {', '.join(sorted(BUILTIN_MODELS))}")
    package, rel = BUILTIN_MODELS[key]
    path = _data_folder(package) / rel
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing from the {package} package; reinstall it ({_INSTALL_HINT})")
    return path


class RobotModel(_earcore.RobotModel):
    """A robot arm: kinematic chain and one padded capsule per link (see the module doc).

    Batched queries take configurations as ``(dof,)`` or ``(K, dof)`` arrays; joints
    outside their limits, NaNs and wrong lengths raise ``ValueError`` naming the joint.
    """

    @classmethod
    def from_urdf(
        cls,
        path: str | Path,
        padding: float = 0.005,
        *,
        geometry: str = "collision",
        shape: Literal["capsule", "cylinder", "auto"] = "auto",
        name: str | None = None,
    ) -> RobotModel:
        """Read a URDF and fit one body per link around its ``geometry`` meshes
        (``collision`` by default, ``visual`` as fallback), grown by ``padding`` metres
        in every direction (Paper II: 5 mm). ``shape`` is ``capsule``, ``cylinder``
        (Paper II's choice) or ``auto``: per link, whichever encloses the mesh with
        less volume (capsules for long round links, cylinders for stubby joints)."""
        if not (np.isfinite(padding) and padding >= 0):
            raise ValueError(f"padding must be finite and >= 0, got {padding}")
        urdf = parse_urdf(path, geometry=geometry)
        index = {link: i for i, link in enumerate(urdf.links)}
        joints = [(j.name, cast(JointKind, j.kind), index[j.parent], index[j.child], j.xyz, j.rpy, j.axis, j.lower, j.upper) for j in urdf.joints]
        bodies = []
        for link in urdf.links:
            vertices = urdf.vertices.get(link)
            bodies.append(None if vertices is None else _earcore.fit_body(vertices, padding, shape))
        try:
            return cls(urdf.links, joints, bodies, name=name or urdf.name, padding=padding)
        except ValueError as exc:  # the core's check of the kinematic tree (a loop, a zero axis...)
            raise UrdfError(f"{path}: {exc}") from exc

    def random_configurations(self, count: int, seed: int | None = None) -> np.ndarray:
        """``count`` configurations uniform within the joint limits (continuous joints in ±π)."""
        limits = np.clip(self.joint_limits, -np.pi, np.pi)
        rng = np.random.default_rng(seed)
        return rng.uniform(limits[:, 0], limits[:, 1], size=(count, self.dof))


def load(name: str, padding: float = 0.005, *, geometry: str = "collision", shape: Literal["capsule", "cylinder", "auto"] = "auto") -> RobotModel:
    """A built-in robot by name: ``ur3``, ``ur5``, ``ur10``, ``iiwa`` or ``panda``."""
    return RobotModel.from_urdf(urdf_path(name), padding, geometry=geometry, shape=shape, name=name.lower())
