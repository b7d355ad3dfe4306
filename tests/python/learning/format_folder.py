"""A small "earcore-images" folder written with the format's own writer (no renderer
needed) for the tests: robots in the manifest's order, one robot per shard, the shards
one robot after another (robot-major, the worst order for "the first N images")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from earcore.learning.shards import Sample, columns, shard_name, write_manifest, write_shard

UR_KEYPOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint", "flange"]
IIWA_KEYPOINTS = [f"lbr_iiwa_joint_{i}" for i in range(1, 8)] + ["flange"]
KEYPOINTS = {"ur3": UR_KEYPOINTS, "ur5": UR_KEYPOINTS, "ur10": UR_KEYPOINTS, "iiwa": IIWA_KEYPOINTS}
DOF = {"ur3": 6, "ur5": 6, "ur10": 6, "iiwa": 7}
#: a typical depth per robot (the camera stands 0.6-1.0 reaches away)
DEPTH = {"ur3": 0.5, "ur5": 0.8, "ur10": 1.0, "iiwa": 0.9}


def write_folder(
    folder: Path, robots=("ur3", "ur10"), per_robot: int | dict[str, int] = 4, width: int = 32, height: int = 24, shard_size: int | None = None, seed: int = 0
) -> Path:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    k = max(len(KEYPOINTS[r]) for r in robots)
    d = max(DOF[r] for r in robots)
    header = columns(d, k)
    rng = np.random.default_rng(seed)
    shards: list[list[Sample]] = []
    for c, robot in enumerate(robots):
        count = per_robot[robot] if isinstance(per_robot, dict) else per_robot
        samples = []
        for i in range(count):
            n = len(KEYPOINTS[robot])
            z = DEPTH[robot] + rng.uniform(-0.05, 0.05, n)
            xyz = np.stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n), z], 1)
            fx = fy = 0.9 * width
            cx, cy = (width - 1) / 2, (height - 1) / 2
            row = {
                "robot": robot,
                "robot_class": c,
                "recording": 0,
                "split": "test" if i % 2 else "train",
                "width": width,
                "height": height,
                "fx": fx,
                "fy": fy,
                "cx": cx,
                "cy": cy,
                "base_x": 0.0,
                "base_y": 0.1,
                "base_z": float(DEPTH[robot]),
                "base_qw": 1.0,
                "base_qx": 0.0,
                "base_qy": 0.0,
                "base_qz": 0.0,
                "coverage": 0.1,
            }
            for j in range(DOF[robot]):
                row[f"q{j}"] = float(rng.uniform(-1, 1))
            for j in range(n):
                u, v = fx * xyz[j, 0] / xyz[j, 2] + cx, fy * xyz[j, 1] / xyz[j, 2] + cy
                row.update({f"kp{j}_x": xyz[j, 0], f"kp{j}_y": xyz[j, 1], f"kp{j}_z": xyz[j, 2], f"kp{j}_u": u, f"kp{j}_v": v, f"kp{j}_in_image": 1})
            rgb = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
            links = np.zeros((height, width), np.uint8)
            links[height // 3 : 2 * height // 3, width // 3 : 2 * width // 3] = 1
            samples.append(Sample(f"{robot}-{i:05d}", {"rgb": rgb, "links": links}, row))
        size = shard_size or count
        shards += [samples[i : i + size] for i in range(0, count, size)]
    for i, s in enumerate(shards):
        write_shard(folder, shard_name(i), s, header)
    write_manifest(
        folder,
        {
            "format": "earcore-images",
            "version": 1,
            "kind": "robots",
            "width": width,
            "height": height,
            "seed": seed,
            "mode": "recordings",
            "robots": list(robots),
            "keypoints": {r: KEYPOINTS[r] for r in robots},
            "num_keypoints": k,
            "links": {r: ["base_link", "link"] for r in robots},
            "max_dof": d,
            "shards": [{"name": shard_name(i), "samples": len(s)} for i, s in enumerate(shards)],
            "generator": {"test": True},
        },
    )
    return folder
