"""A rerun recording (.rrd) of the simulated cell: camera images and poses, the points
inserted into the map, the robot's bodies, the person's arm (ground truth), occupied
voxels coloured by danger, the current obstacles and per-stage timings. Open it with
`rerun out/cell.rrd` (`pip install rerun-sdk`).

Heavy items are logged at `heavy_rate_hz` to keep the file small (~1 MB per second
simulated with the default cameras).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from earcore.transforms import turn_from_z

__all__ = ["Recorder"]


def _rerun():
    try:
        import rerun as rr
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("recordings need rerun: pip install 'earcore[viz]'") from exc
    return rr


def _danger_colours(values: np.ndarray) -> np.ndarray:
    """Yellow (low) to dark red (0.999), as uint8 RGB."""
    v = np.clip(values, 0, 1)[:, None]
    low, high = np.array([255, 237, 160]), np.array([128, 0, 38])
    return (low + (high - low) * v).astype(np.uint8)


class Recorder:
    def __init__(self, path: Path, *, heavy_rate_hz: float = 2.0) -> None:
        rr = _rerun()
        self.rr = rr
        self.path = Path(path)
        self.stream = rr.RecordingStream("earcore", recording_id="earcore-cell")
        self.stream.save(str(self.path))
        self.heavy_period = 1.0 / heavy_rate_hz
        self._next_heavy = 0.0
        self._static_cameras: set[str] = set()

    def log_frame(self, time_s: float, cell, pipeline, frames, report, executive=None) -> None:
        rr, rec = self.rr, self.stream
        rec.set_time("sim", duration=time_s)
        heavy = time_s + 1e-9 >= self._next_heavy
        if heavy:
            self._next_heavy += self.heavy_period
        # The robot's bodies and the person's arm (truth), every frame.
        bodies = cell.model.bodies(cell.q)
        self._capsules("world/robot", bodies["a"], bodies["b"], bodies["radius"], (70, 130, 180))
        segments = cell.person_segments()
        if segments:
            a, b, r = zip(*segments)
            self._capsules("world/person_truth", np.array(a), np.array(b), np.array(r), (60, 170, 75))
        for frame in frames:
            path = f"world/cameras/{frame.camera}"
            pose = frame.base_from_camera
            if frame.camera not in self._static_cameras or frame.camera.startswith("f200"):
                rec.log(path, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
                h, w = frame.depth.shape
                rec.log(path, rr.Pinhole(image_from_camera=frame.K, resolution=[w, h]))
                self._static_cameras.add(frame.camera)
            if heavy:
                rec.log(f"{path}/rgb", rr.Image(frame.colour).compress(jpeg_quality=70))
                rec.log(f"{path}/depth", rr.DepthImage((frame.depth * 1000).astype(np.uint16), meter=1000.0))
        if executive is not None and hasattr(executive, "log"):
            self._log_planning(cell, executive)
        rec.log("timings/perception_ms", rr.Scalars(1e3 * report.total))
        for stage, seconds in report.timings.items():
            rec.log(f"timings/{stage}_ms", rr.Scalars(1e3 * seconds))
        if heavy:
            centres, sizes, values = pipeline.tree.danger_voxels()
            rec.log(
                "world/map/danger",
                rr.Boxes3D(centers=centres, half_sizes=np.repeat(sizes[:, None] / 2, 3, axis=1), colors=_danger_colours(values), fill_mode="solid"),
            )
            obstacles, osizes = pipeline.tree.current_obstacles()
            rec.log("world/map/current_obstacles", rr.Points3D(obstacles, radii=osizes / 2, colors=(220, 40, 40)))

    def log_pose(self, time_s: float, camera: str, picture) -> None:
        """The pose network's estimate drawn over the camera's image (papers' convention:
        true joints green crosses, estimated red circles, base magenta, mask tinted)."""
        self.stream.set_time("sim", duration=time_s)
        self.stream.log(f"world/cameras/{camera}/pose", self.rr.Image(picture))

    def _log_planning(self, cell, executive) -> None:
        """The path being executed (the tool's line), new plans and reflexes, the risk."""
        rr, rec = self.rr, self.stream
        log = executive.log
        if executive.motion is not None and executive.motion.trajectory is not getattr(self, "_shown", None):
            self._shown = executive.motion.trajectory
            tool = cell.model.fk(self._shown.positions)[:, -1, :3, 3]
            colour = (230, 140, 20) if executive.motion.kind in ("reflex", "backtrack") else (40, 90, 220)
            rec.log("world/plan/tool_path", rr.LineStrips3D([tool], colors=[colour], radii=0.004))
        for event in log.reflexes[getattr(self, "_reflexes_shown", 0):]:
            rec.log("events/reflex", rr.TextLog(f"reflex: {event['kind']} (risk {event.get('risk', 0.0):.2f})", level="WARN"))
        self._reflexes_shown = len(log.reflexes)
        if log.risk:
            rec.log("planning/risk", rr.Scalars(min(log.risk[-1].risk, 10.0)))

    def _capsules(self, path: str, a: np.ndarray, b: np.ndarray, radii: np.ndarray, colour) -> None:
        rr = self.rr
        axis = b - a
        lengths = np.linalg.norm(axis, axis=1)
        quats = []
        for d, n in zip(axis, lengths):
            turn, angle = turn_from_z(d if n > 0 else (0.0, 0.0, 1.0))
            quats.append([*(np.sin(angle / 2) * turn), np.cos(angle / 2)])
        self.stream.log(
            path,
            rr.Capsules3D(lengths=lengths, radii=radii, translations=a, quaternions=[rr.Quaternion(xyzw=q) for q in quats], colors=colour),
        )

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()
