"""Robot pose from one colour image (Papers IV and V): the robot's mask, its keypoints
and base in the camera frame, and its type.

- `estimate(image, camera)` → `PoseEstimate`, with onnxruntime and numpy only (module
  `inference`: a module named `estimate` would shadow the function);
- `earcore.pose.networks` (torch): Paper IV's cascade, Paper V's multi-objective network,
  a keypoint-heatmap variant; `objectives`, `evaluate`, `train` (runnable as
  ``python -m earcore.pose.train``, without the compiled core), `export`;
- `refine`: joint angles and base pose fitted to keypoints through forward kinematics;
  PnP for the base when the joint angles are known;
- `overlay`: pictures in the papers' convention.

Importing this package imports neither torch nor onnxruntime.
"""

from __future__ import annotations

from earcore.pose.errors import PoseError, PoseWeightsError
from earcore.pose.inference import PoseEstimate, estimate  # numpy only; onnxruntime when called

__all__ = ["NETWORKS", "PoseEstimate", "PoseError", "PoseWeightsError", "estimate"]

#: the networks `earcore.pose.networks.build_network` knows (that module needs torch)
NETWORKS = ("multi", "cascade", "keypoint")
