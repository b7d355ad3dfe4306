"""A compliant tool holder in pybullet: a free body (the charging plug) held at the
flange's target pose by a spring-damper, stiff along the tool's axis and soft across it
and in rotation, as the passive compliance of a peg-in-hole tool. The holder's force on
the body is what a wrist force sensor reads (the body's weight is compensated, as the
robot's payload setting does).

    holder = CompliantHolder(client, body, Compliance(), mass=1.5, inertia=(3e-3, 3e-3, 2e-3))
    force = holder.apply(base_from_target, velocity, angular_velocity)   # then stepSimulation()
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from earcore.transforms import rotation_vector

__all__ = ["Compliance", "CompliantHolder"]


@dataclass(frozen=True)
class Compliance:
    """Stiffness along the tool's z (N/m), across it (N/m) and in rotation (N·m/rad)."""

    axial: float = 5.0e4
    lateral: float = 5.0e3
    rotational: float = 20.0

    def __post_init__(self) -> None:
        if min(self.axial, self.lateral, self.rotational) <= 0:
            raise ValueError(f"stiffnesses must be positive, got {self}")


class CompliantHolder:
    """Each `apply` sets this tick's spring-damper force and torque on `body` (critically
    damped for its `mass` and `inertia`) plus the compensation of its weight; the force
    applies to the next `stepSimulation` only, so call it every tick."""

    def __init__(self, client, body: int, compliance: Compliance, mass: float, inertia, gravity: float = 9.81) -> None:
        self.p = client
        self.body = body
        self.compliance = compliance
        self.mass = float(mass)
        self.stiffness = np.array([compliance.lateral, compliance.lateral, compliance.axial])
        self.damping = 2.0 * np.sqrt(self.stiffness * self.mass)
        self.rotational_damping = 2.0 * np.sqrt(compliance.rotational * float(np.max(inertia)))
        self.weight = np.array([0.0, 0.0, self.mass * gravity])

    def apply(self, base_from_target: np.ndarray, velocity: np.ndarray, angular_velocity=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Push the body towards `base_from_target` moving at `velocity` (m/s, base
        frame) and turning at `angular_velocity` (rad/s, base frame); return the spring-damper's force on the body in the target's frame (N;
        the weight's compensation left out: what a tared wrist sensor reads)."""
        p = self.p
        position, orientation = p.getBasePositionAndOrientation(self.body)
        linear, angular = p.getBaseVelocity(self.body)
        rotation = base_from_target[:3, :3]
        error = rotation.T @ (base_from_target[:3, 3] - np.asarray(position))
        rate = rotation.T @ (np.asarray(velocity, dtype=np.float64) - np.asarray(linear))
        local = self.stiffness * error + self.damping * rate
        body_rotation = np.reshape(p.getMatrixFromQuaternion(orientation), (3, 3))
        turn = np.asarray(angular_velocity, dtype=np.float64) - np.asarray(angular)
        torque = self.compliance.rotational * rotation_vector(rotation @ body_rotation.T) + self.rotational_damping * turn
        p.applyExternalForce(self.body, -1, (rotation @ local + self.weight).tolist(), position, p.WORLD_FRAME)
        p.applyExternalTorque(self.body, -1, torque.tolist(), p.WORLD_FRAME)
        return local
