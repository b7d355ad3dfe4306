"""The charging cell of Paper III in pybullet: a UR10 on a post, a verging stereo pair of
colour cameras behind it, and the side of a parked car with a charging port.

    cell = ChargingCell(ChargingCellConfig(seed=3))
    left, right = cell.capture()                 # colour images with sensor noise
    cell.base_from_port                          # the truth, for evaluation only
    cell.rig                                     # the pair as a StereoRig (true poses)

Layout (the robot's base frame, z up): the robot stands on a post with its base at the
origin; the car's side faces it about a metre away along +y; the stereo pair stands
behind the robot, its midpoint at `rig_position`: the left camera aimed at the nominal
port, the right one beside it turned about its vertical axis to look there too (the
paper's "looking slightly inwards", Eq. 1's geometry), so the port is about 2 m away. Parking is
imperfect (`park`): the port lands anywhere in a square of `parking_area` on the car's
side, its axis `min_angle_deg` to `max_angle_deg` off the direction to the cameras, turned about its
axis by up to `max_roll_deg` (a car on a slope).

The port is black plastic installed as `charging.connectors` describes: a round collar
around a face recessed into it, a dark gap to the car's body, one hole per contact (the
hole floors darker). The plug (Type 2 by default) rides on the
flange in a holder, pointing along the flange's z (`flange_from_tip`).

Physics: the robot is kinematic (`set_joints` for moves in free space, `servo` for one
1 ms control tick). The plug is a free body in a compliant holder
(`sim.compliant_holder`) whose force is the wrist sensor's reading; the port, its collar
and the car's side are concave triangle meshes, so a pin meets the face unless it is
within its hole's 0.4 mm clearance (or its round tip leads it in). `drive_away` takes the
car out (the station calibrates then).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from earcore import robots
from earcore.charging.connectors import COLLAR, GAP, RECESS, Connector, connector, hole_polygon
from earcore.charging.stereo import StereoRig, verging_pose
from earcore.errors import ConfigError
from earcore.mesh import Mesh, circle, densify, extrude, offset_polygon
from earcore.sim.camera import SimulatedCamera
from earcore.sim.compliant_holder import Compliance, CompliantHolder
from earcore.sim.sensors import SENSORS
from earcore.transforms import axis_angle_matrix, look_at, quaternion, rotation_vector

__all__ = ["ChargingCell", "ChargingCellConfig", "Parking", "STANDBY"]

#: Collision margin and friction of the plug and the port (m): pybullet's default margin
#: (1 mm) would close the pins' 0.4 mm clearance.
CONTACT_MARGIN = 1e-4
FRICTION = 0.3
#: The plug's length behind its front face, and of its shell's front rim in the physics (m).
PLUG_LENGTH = 0.04
SHELL_RIM = 0.005

#: The UR10's stand-by joints: arm folded up and turned aside, clear of the cameras' view.
STANDBY = np.array([-np.pi / 2, -2.4, 2.3, -1.5, -np.pi / 2, 0.0])


@dataclass(frozen=True)
class ChargingCellConfig:
    seed: int = 0
    #: The car's port and the robot's plug (`charging.connectors` names).
    port: str = "type2"
    plug: str = "type2"
    robot: str = "ur10"
    #: The port's nominal centre in the base frame (m) and the car side's normal there.
    port_nominal: tuple[float, float, float] = (0.0, 1.0, 0.15)
    parking_area: float = 0.20
    max_angle_deg: float = 45.0
    min_angle_deg: float = 0.0
    max_roll_deg: float = 5.0
    #: The stereo pair: its midpoint, baseline (m) and camera model (`SENSORS`).
    rig_position: tuple[float, float, float] = (-0.6, -0.8, 0.7)
    #: Where the left camera looks (default: the nominal port).
    camera_target: tuple[float, float, float] | None = None
    baseline: float = 0.6
    sensor: str = "machine_vision"
    #: The cameras' resolution as a fraction of the sensor's (quick runs and tests).
    camera_scale: float = 1.0
    #: The images' noise: Gaussian, in grey levels.
    image_noise: float = 2.0
    #: The plug's tip from the flange: along the flange's z (m).
    tip_offset: float = 0.14
    #: The plug's mass with the share of its cable's weight the holder carries (kg).
    plug_mass: float = 0.5
    cable_mass: float = 1.0
    #: The plug holder's passive compliance and the physics' time step (s).
    compliance: Compliance = field(default_factory=Compliance)
    time_step: float = 0.001
    car_colours: tuple[tuple[float, float, float], ...] = field(
        default=((0.55, 0.05, 0.05), (0.1, 0.2, 0.45), (0.75, 0.75, 0.75), (0.95, 0.95, 0.93), (0.25, 0.28, 0.35), (0.15, 0.35, 0.2))
    )

    def validate(self) -> ChargingCellConfig:
        connector(self.port), connector(self.plug)
        if self.sensor not in SENSORS or SENSORS[self.sensor].has_depth:
            colour = ", ".join(k for k, s in SENSORS.items() if not s.has_depth)
            raise ConfigError(f"charging cell: sensor must be a colour camera ({colour}), got {self.sensor!r}")
        if not 0 <= self.min_angle_deg <= self.max_angle_deg <= 55:
            raise ConfigError(
                f"charging cell: need 0 <= min_angle_deg <= max_angle_deg <= 55 (beyond, the port is seen too edge-on to match), "
                f"got {self.min_angle_deg}, {self.max_angle_deg}"
            )
        if not 0 < self.camera_scale <= 1:
            raise ConfigError(f"charging cell: camera_scale must be in (0, 1], got {self.camera_scale}")
        if not 0 < self.time_step <= 0.002 or self.plug_mass <= 0 or self.cable_mass < 0:
            raise ConfigError("charging cell: time_step must be in (0, 2 ms] (contacts at the pins' clearance) and the masses positive")
        if self.baseline <= 0 or self.parking_area < 0:
            raise ConfigError("charging cell: baseline must be positive and parking_area not negative")
        return self


@dataclass(frozen=True)
class Parking:
    """Where the car stopped: the port's pose in the base frame, its axis' angle to the
    direction of the cameras (degrees) and its turn about its own axis (degrees)."""

    base_from_port: np.ndarray
    angle_deg: float
    roll_deg: float


def _upright_port(normal: np.ndarray) -> np.ndarray:
    """A rotation with z = `normal` and y as close to the world's up as it can be."""
    z = normal / np.linalg.norm(normal)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], 1)


class ChargingCell:
    def __init__(self, config: ChargingCellConfig | None = None) -> None:
        import pybullet
        from pybullet_utils.bullet_client import BulletClient

        self.config = c = (config or ChargingCellConfig()).validate()
        self.rng = np.random.default_rng(c.seed)
        self.port_connector: Connector = connector(c.port)
        self.plug_connector: Connector = connector(c.plug)
        self.p = p = BulletClient(pybullet.DIRECT)
        p.setGravity(0, 0, -9.81)
        p.setPhysicsEngineParameter(fixedTimeStep=c.time_step, numSolverIterations=50)
        #: Simulated seconds the physics has run.
        self.time = 0.0
        self._static = self._build_static()
        self.robot_id = p.loadURDF(str(robots.urdf_path(c.robot)), useFixedBase=True)
        self.joint_ids = [j for j in range(p.getNumJoints(self.robot_id)) if p.getJointInfo(self.robot_id, j)[2] != p.JOINT_FIXED]
        names = [p.getJointInfo(self.robot_id, j)[12].decode() for j in range(p.getNumJoints(self.robot_id))]
        self._flange = names.index(robots.FLANGES[c.robot][0])
        self.flange_from_tip = np.eye(4)
        self.flange_from_tip[:3, :3] = axis_angle_matrix([1.0, 0.0, 0.0], np.pi)  # the pins point along the flange's z
        self.flange_from_tip[2, 3] = c.tip_offset
        self._plug = self._build_plug()
        self.plug_id, self.holder = self._build_plug_physics()
        self._last_target: np.ndarray | None = None
        #: A light above and behind the cameras, ambient enough for black plastic to show.
        self.lighting = {"lightDirection": [-0.3, -1.0, 1.5], "lightAmbientCoeff": 0.45, "lightDiffuseCoeff": 0.6, "lightSpecularCoeff": 0.0, "shadow": 0}
        self._port_bodies: list[int] = []
        self.parking = self.park()
        self.set_joints(STANDBY)
        self.cameras = self._build_cameras()

    # -- the scene ---------------------------------------------------------------------------

    def _mesh_body(self, mesh: Mesh, pose: np.ndarray, colour, collision: bool = False) -> int:
        p = self.p
        vertices, indices = mesh.vertices.tolist(), mesh.triangles.ravel().tolist()
        # flat shading with the faces' own normals (pybullet's guessed normals band across
        # large faces): edges stay edges, planes stay even
        flat = mesh.unshared()
        normals = np.repeat(mesh.face_normals(), 3, axis=0).tolist()
        visual = p.createVisualShape(
            p.GEOM_MESH, vertices=flat.vertices.tolist(), indices=flat.triangles.ravel().tolist(), normals=normals, rgbaColor=[*colour, 1.0]
        )
        shape = p.createCollisionShape(p.GEOM_MESH, vertices=vertices, indices=indices, flags=p.GEOM_FORCE_CONCAVE_TRIMESH) if collision else -1
        body = p.createMultiBody(0, shape, visual, pose[:3, 3].tolist(), list(quaternion(pose[:3, :3])))
        if collision:
            p.changeDynamics(body, -1, collisionMargin=CONTACT_MARGIN, lateralFriction=FRICTION)
        return body

    def _box(self, centre, half, rotation: np.ndarray, colour) -> int:
        p = self.p
        shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half))
        visual = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half), rgbaColor=[*colour, 1.0])
        return p.createMultiBody(0, shape, visual, list(centre), list(quaternion(rotation)))

    def _build_static(self) -> list[int]:
        floor = self._box((0.0, 0.0, -1.02), (4.0, 4.0, 0.02), np.eye(3), (0.55, 0.55, 0.52))
        post = self._box((0.0, 0.0, -0.52), (0.08, 0.08, 0.5), np.eye(3), (0.35, 0.35, 0.38))
        return [floor, post]

    def drive_away(self) -> None:
        """Take the car out of the cell (until the next `park`)."""
        for body in self._port_bodies:
            self.p.removeBody(body)
        self._port_bodies = []

    def park(self, rng: np.random.Generator | None = None) -> Parking:
        """Put the car's side and its port at a new random place (imperfect parking)."""
        c = self.config
        rng = self.rng if rng is None else rng
        self.drive_away()
        nominal = np.asarray(c.port_nominal, dtype=np.float64)
        facing = _upright_port(np.asarray(c.rig_position) - nominal)
        centre = nominal + facing[:, 0] * rng.uniform(-0.5, 0.5) * c.parking_area + facing[:, 1] * rng.uniform(-0.5, 0.5) * c.parking_area
        to_cameras = np.asarray(c.rig_position) - centre
        to_cameras /= np.linalg.norm(to_cameras)
        # the axis: the direction to the cameras tipped by the angle about a random line across it
        angle = float(rng.uniform(c.min_angle_deg, c.max_angle_deg))
        across = np.cross(to_cameras, rng.normal(size=3))
        axis = axis_angle_matrix(across / np.linalg.norm(across), np.radians(angle)) @ to_cameras
        roll = float(rng.uniform(-c.max_roll_deg, c.max_roll_deg))
        pose = np.eye(4)
        pose[:3, :3] = _upright_port(axis) @ axis_angle_matrix([0.0, 0.0, 1.0], np.radians(roll))
        pose[:3, 3] = centre
        self._port_bodies = self._build_port(pose, rng)
        self.parking = Parking(pose, angle, roll)
        return self.parking

    def _build_port(self, base_from_port: np.ndarray, rng: np.random.Generator) -> list[int]:
        k = self.port_connector
        depth = k.hole_depth + 0.011
        port = self._mesh_body(k.port_mesh(depth), base_from_port, (0.10, 0.10, 0.105), collision=True)
        # the collar: a ring around the face, its front RECESS ahead of it
        outer = circle(k.radius + COLLAR)
        collar_depth = depth + RECESS
        collar_pose = base_from_port.copy()
        collar_pose[:3, 3] = base_from_port[:3, :3] @ [0.0, 0.0, RECESS] + base_from_port[:3, 3]
        collar = self._mesh_body(extrude(outer, collar_depth, [(k.outline, collar_depth - 0.0005)]), collar_pose, (0.17, 0.17, 0.18), collision=True)
        # the recess' wall in the face's plastic (a thin sleeve inside the collar's opening,
        # for the eye only): the face's outline is then sharp at the collar's front
        inset = offset_polygon(k.outline, -0.0003)
        sleeve_pose = base_from_port.copy()
        sleeve_pose[:3, 3] = base_from_port[:3, :3] @ [0.0, 0.0, RECESS - 0.0001] + base_from_port[:3, 3]
        sleeve_depth = RECESS - 0.0002
        sleeve = self._mesh_body(extrude(k.outline, sleeve_depth, [(inset, sleeve_depth)]), sleeve_pose, (0.10, 0.10, 0.105))
        # the holes' floors, darker than the plastic (no ambient occlusion in the renderer)
        floors = Mesh.union([extrude(hole_polygon(ct.x, ct.y, k.hole_radius(ct)), 0.0005) for ct in k.contacts])
        floor_pose = base_from_port.copy()
        floor_pose[:3, 3] = base_from_port[:3, :3] @ [0.0, 0.0, -k.hole_depth + 0.0006] + base_from_port[:3, 3]
        dark = self._mesh_body(floors, floor_pose, (0.01, 0.01, 0.01))
        # the car's side, flush with the collar's front, the car's colour
        colour = self.config.car_colours[int(rng.integers(len(self.config.car_colours)))]
        # (evenly meshed: the renderer shades per vertex, so long thin triangles would band)
        side = densify(np.array([[-0.7, -0.45], [0.7, -0.45], [0.7, 0.45], [-0.7, 0.45]]), 0.03)
        # with the gap every inlet has between its housing and the body (dark, GAP wide)
        thickness = collar_depth + 0.01
        opening = circle(k.radius + COLLAR + GAP)
        panel = self._mesh_body(extrude(side, thickness, [(opening, thickness - 0.0005)], spacing=0.03), collar_pose, colour, collision=True)
        gap_pose = collar_pose.copy()
        gap_pose[:3, 3] = collar_pose[:3, :3] @ [0.0, 0.0, -0.001] + collar_pose[:3, 3]  # shallow: its walls hide little at an angle
        gap = self._mesh_body(extrude(opening, 0.0005, [(outer, 0.0005)]), gap_pose, (0.02, 0.02, 0.02))
        return [port, collar, sleeve, dark, panel, gap]

    def _build_plug(self) -> list[int]:
        """The plug as the cameras see it (no collision; placed where the physics' plug is)."""
        k = self.plug_connector
        body = self._mesh_body(k.plug_body_mesh(PLUG_LENGTH), np.eye(4), (0.12, 0.12, 0.13))
        # matt plastic (the renderer's default specular would paint it light grey), shiny pins
        self.p.changeVisualShape(body, -1, specularColor=[0.05, 0.05, 0.05])
        pins = self._mesh_body(Mesh.union(k.pin_meshes()), np.eye(4), (0.75, 0.68, 0.45))
        return [body, pins]

    def _build_plug_physics(self) -> tuple[int, CompliantHolder]:
        """The plug as the physics sees it, a free body in its tip frame: one capsule
        per pin (round tips, as real pins have: they lead a pin into its hole within
        about its radius) and the front rim of the shell behind the nose, which stops on
        the collar's front when the plug is fully in. The nose itself is left out: its
        clearance (0.5 mm) is wider than the pins' and they guide it."""
        c, p, k = self.config, self.p, self.plug_connector
        types, radii, lengths, frames = [], [], [], []
        for ct in k.contacts:
            types.append(p.GEOM_CAPSULE)
            radii.append(ct.radius)
            lengths.append(k.pin_length - 2 * ct.radius)
            frames.append([ct.x, ct.y, -k.pin_length / 2])
        types.append(p.GEOM_CYLINDER)
        radii.append(k.radius + COLLAR)
        lengths.append(SHELL_RIM)
        frames.append([0.0, 0.0, RECESS + SHELL_RIM / 2])
        shape = p.createCollisionShapeArray(shapeTypes=types, radii=radii, lengths=lengths, collisionFramePositions=frames)
        mass = c.plug_mass + c.cable_mass
        inertia = (3e-3, 3e-3, 2e-3)  # the plug with its cable's stiff first part
        # a speck of a visual inside the plug: a body without one is drawn with its
        # collision shapes, over the plug the cameras should see
        speck = p.createVisualShape(p.GEOM_SPHERE, radius=1e-4, visualFramePosition=[0.0, 0.0, PLUG_LENGTH / 2])
        body = p.createMultiBody(mass, shape, speck)
        p.changeDynamics(body, -1, collisionMargin=CONTACT_MARGIN, lateralFriction=FRICTION, localInertiaDiagonal=inertia, linearDamping=0.0, angularDamping=0.0)
        for link in range(-1, p.getNumJoints(self.robot_id)):
            p.setCollisionFilterPair(body, self.robot_id, -1, link, 0)
        return body, CompliantHolder(p, body, c.compliance, mass, inertia)

    def _build_cameras(self) -> list[SimulatedCamera]:
        c = self.config
        sensor = SENSORS[c.sensor] if c.camera_scale == 1.0 else SENSORS[c.sensor].scaled(c.camera_scale)
        middle = np.asarray(c.rig_position, dtype=np.float64)
        target = np.asarray(c.port_nominal if c.camera_target is None else c.camera_target, dtype=np.float64)
        forward = (target - middle) / np.linalg.norm(target - middle)
        side = np.cross(forward, [0.0, 0.0, 1.0])
        side /= np.linalg.norm(side)
        # the paper's pair (Eq. 1's geometry): the left camera aimed at the nominal port,
        # the right one beside it along its x, turned about its y until their axes cross there
        left = look_at(middle - side * c.baseline / 2, target)
        vergence = np.degrees(np.arctan2(c.baseline, np.linalg.norm(target - left[:3, 3])))
        right = left @ verging_pose(c.baseline, vergence)
        rng = np.random.default_rng
        return [
            SimulatedCamera(self.p, name, sensor, pose, rng=rng([c.seed, k]), lighting=self.lighting)
            for k, (name, pose) in enumerate((("left", left), ("right", right)))
        ]

    # -- the robot -----------------------------------------------------------------------------

    def _set_robot(self, q) -> None:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (len(self.joint_ids),) or not np.isfinite(q).all():
            raise ValueError(f"expected {len(self.joint_ids)} finite joints, got shape {q.shape}")
        for j, v in zip(self.joint_ids, q):
            self.p.resetJointState(self.robot_id, j, float(v))

    def set_joints(self, q) -> None:
        """Put the robot at `q` and the plug in its holder at rest (motion in free space:
        no physics)."""
        self._set_robot(q)
        pose = self.base_from_tip()
        self.p.resetBasePositionAndOrientation(self.plug_id, pose[:3, 3].tolist(), list(quaternion(pose[:3, :3])))
        self.p.resetBaseVelocity(self.plug_id, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
        self._last_target = pose
        self._place_plug()

    def servo(self, q) -> np.ndarray:
        """One physics tick with the robot commanded to `q`: the holder pulls the plug
        towards the flange's tip pose, contacts push back. Returns the wrist sensor's
        force on the plug in the tip frame (N): z < 0 pushes the plug along its pins."""
        self._set_robot(q)
        target = self.base_from_tip()
        last = target if self._last_target is None else self._last_target
        velocity = (target[:3, 3] - last[:3, 3]) / self.config.time_step
        turning = rotation_vector(target[:3, :3] @ last[:3, :3].T) / self.config.time_step
        force = self.holder.apply(target, velocity, turning)
        self.p.stepSimulation()
        self._last_target = target
        self.time += self.config.time_step
        return force

    def base_from_plug(self) -> np.ndarray:
        """Where the plug's tip frame truly is (it lags the flange in contact)."""
        position, orientation = self.p.getBasePositionAndOrientation(self.plug_id)
        m = np.eye(4)
        m[:3, :3] = np.reshape(self.p.getMatrixFromQuaternion(orientation), (3, 3))
        m[:3, 3] = position
        return m

    def plug_contact_force(self) -> float:
        """The sum of the normal forces between the plug and the car (N), the truth the
        wrist sensor's reading approximates."""
        return float(sum(c[9] for c in self.p.getContactPoints(self.plug_id)))

    @property
    def joints(self) -> np.ndarray:
        return np.array([self.p.getJointState(self.robot_id, j)[0] for j in self.joint_ids])

    def base_from_flange(self) -> np.ndarray:
        state = self.p.getLinkState(self.robot_id, self._flange, computeForwardKinematics=True)
        m = np.eye(4)
        m[:3, :3] = np.reshape(self.p.getMatrixFromQuaternion(state[5]), (3, 3))
        m[:3, 3] = state[4]
        return m

    def base_from_tip(self) -> np.ndarray:
        return self.base_from_flange() @ self.flange_from_tip

    def _place_plug(self) -> None:
        pose = self.base_from_plug()
        x, y, z, w = quaternion(pose[:3, :3])
        for body in self._plug:
            self.p.resetBasePositionAndOrientation(body, pose[:3, 3].tolist(), [x, y, z, w])

    # -- seeing ----------------------------------------------------------------------------------

    @property
    def base_from_port(self) -> np.ndarray:
        return self.parking.base_from_port.copy()

    @property
    def rig(self) -> StereoRig:
        """The stereo pair with its true intrinsics and relative pose."""
        left, right = self.cameras
        sensor = left.sensor
        dist = np.asarray(sensor.distortion, dtype=np.float64)
        right_from_left = np.linalg.inv(right.base_from_camera) @ left.base_from_camera
        return StereoRig(sensor.intrinsics, sensor.intrinsics, right_from_left, dist, dist.copy(), (sensor.width, sensor.height))

    def capture(self) -> tuple[np.ndarray, np.ndarray]:
        """Both cameras' colour images (H, W, 3 uint8) with the sensor's noise."""
        self._place_plug()
        out = []
        for camera in self.cameras:
            image = camera.render_colour().astype(np.float64)
            if self.config.image_noise > 0:
                image += camera.rng.normal(0.0, self.config.image_noise, image.shape)
            out.append(np.clip(np.rint(image), 0, 255).astype(np.uint8))
        return out[0], out[1]

    def close(self) -> None:
        self.p.disconnect()
