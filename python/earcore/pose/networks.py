"""The pose networks (torch): Paper IV's cascade, Paper V's multi-objective network and
a keypoint variant beyond the papers. Every network maps an image (N, 3, H, W) float32
in [0, 1] to a dict:

- "mask_logits" (N, 1, H, W): the robot mask before the sigmoid;
- "keypoints" (N, K, 3): keypoints in the camera frame, metres (OpenCV axes, z forward);
- "base" (N, 3): the robot base in the camera frame, metres;
- "type_logits" (N, R): the robot type (absent for the cascade, which the paper trained
  per robot);
- the keypoint network adds "pixels" (N, K + 1, 2): its 2D keypoints (base last).

**Input size.** A network is built for one size (`input_size` = (W, H), both >= 16; the
papers' 256×212 and the shipped 128×106 included). The fully connected layers need it;
pooling rounds up (ceil mode), so no size needs to be divisible by anything. Another
size is a `ValueError` naming the expected one (`earcore.pose.estimate` resizes).

**What the papers leave open, and what is chosen here** (each an option):
activations ReLU; batch normalisation after every convolution (trains fast on small
batches; folded into the convolution by ONNX export); "same" padding for 3×3
convolutions (padding = dilation), so the mask stays at input resolution; the input is
centred inside the network ((x - 0.5) / 0.25). The fully connected layers read a
feature map max-pooled (ceil mode) until both sides are at most `grid` (8): the papers'
three pools at 256×212 leave a 32×27×128 map, i.e. 113 M weights in FC 1024; 8×7 keeps
the spatial layout the regression needs with 7 M. Outputs are standardised: the
network predicts (p - mean) / std per axis, with mean and std of the training
keypoints stored as buffers (`set_output_statistics`), so metres come out and the
regression starts at a sensible scale. `mask_stride` 2 computes the mask branch at half
resolution (first convolution strided) and upsamples its logits bilinearly: 4× fewer
operations in the widest layers (the papers: stride 1).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from earcore.errors import ConfigError

__all__ = [
    "NETWORKS",
    "PRESETS",
    "CascadeNet",
    "KeypointNet",
    "MultiObjectiveNet",
    "NetworkOptions",
    "build_network",
]

NETWORKS = ("multi", "cascade", "keypoint")


@dataclass
class NetworkOptions:
    """A network's shape. `width` scales every convolution's filters (1 = the papers'
    32/64/128); `fc` is the shared fully connected layer (Paper V: 1024, Paper IV's
    regressor: 500), `head` each output head's hidden layer (Paper V: 512)."""

    input_size: tuple[int, int] = (128, 106)
    num_keypoints: int = 7
    num_robots: int = 3
    width: float = 1.0
    fc: int = 1024
    head: int = 512
    mask_stride: int = 1
    grid: int = 8
    norm: str = "batch"
    activation: str = "relu"
    #: dilations of the mask branch after the first convolution (Paper V's reconstruction: 5, 3, 5, 3)
    mask_dilations: list[int] = field(default_factory=lambda: [5, 3, 5, 3])
    #: the keypoint network's heatmap stride (4: 32×27 heatmaps at 128×106)
    heatmap_stride: int = 4
    #: the keypoint network only: > 1 reads boxes around the robot cut from images this
    #: many times the input size (a first look at the whole image shrunk places the box;
    #: `earcore.pose.zoom`); depths then follow each box's focal length
    zoom: int = 1

    def __post_init__(self) -> None:
        self.input_size = tuple(self.input_size)  # type: ignore[assignment]
        self.mask_dilations = list(self.mask_dilations)
        self.validate()

    def validate(self) -> None:
        if len(self.input_size) != 2 or not all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= 4096 for v in self.input_size):
            raise ConfigError(f"input_size must be (width, height) whole numbers in [16, 4096], got {self.input_size!r}")
        for name, low, high in (("num_keypoints", 1, 256), ("num_robots", 1, 1024), ("fc", 1, 65536), ("head", 1, 65536), ("grid", 1, 64)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ConfigError(f"{name} must be a whole number in [{low}, {high}], got {value!r}")
        if isinstance(self.width, bool) or not isinstance(self.width, (int, float)) or not 0.05 <= self.width <= 8:
            raise ConfigError(f"width must be in [0.05, 8], got {self.width!r}")
        if self.mask_stride not in (1, 2, 4):
            raise ConfigError(f"mask_stride must be 1, 2 or 4, got {self.mask_stride!r}")
        if self.heatmap_stride not in (2, 4, 8):
            raise ConfigError(f"heatmap_stride must be 2, 4 or 8, got {self.heatmap_stride!r}")
        if isinstance(self.zoom, bool) or not isinstance(self.zoom, int) or not 1 <= self.zoom <= 8:
            raise ConfigError(f"zoom must be a whole number in [1, 8], got {self.zoom!r}")
        if self.norm not in ("batch", "group", "none"):
            raise ConfigError(f"norm must be 'batch', 'group' or 'none', got {self.norm!r}")
        if self.activation not in ("relu", "elu", "leaky"):
            raise ConfigError(f"activation must be 'relu', 'elu' or 'leaky', got {self.activation!r}")
        if not self.mask_dilations or not all(isinstance(d, int) and not isinstance(d, bool) and 1 <= d <= 16 for d in self.mask_dilations):
            raise ConfigError(f"mask_dilations must be a non-empty list of whole numbers in [1, 16], got {self.mask_dilations!r}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> NetworkOptions:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown network option(s) {', '.join(map(repr, unknown))}; known: {', '.join(sorted(known))}")
        return cls(**data)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["input_size"] = list(self.input_size)
        return d

    def channels(self, n: int) -> int:
        return max(4, int(round(n * self.width)))


#: Named shapes: "paper" is the papers' size (Paper V at 256×212, the papers' filters and
#: FC sizes; the mask branch at half resolution: at full resolution one forward pass takes
#: 35 ms on one core, 11 ms at half); "small" the shipped one (128×106, half the filters,
#: mask at half resolution).
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {"input_size": (256, 212), "width": 1.0, "fc": 1024, "head": 512, "mask_stride": 2},
    "small": {"input_size": (128, 106), "width": 0.5, "fc": 256, "head": 128, "mask_stride": 2},
}


def _activation(options: NetworkOptions) -> nn.Module:
    if options.activation == "elu":
        return nn.ELU(inplace=True)
    if options.activation == "leaky":
        return nn.LeakyReLU(0.1, inplace=True)
    return nn.ReLU(inplace=True)


def _norm(options: NetworkOptions, channels: int) -> nn.Module:
    if options.norm == "batch":
        return nn.BatchNorm2d(channels)
    if options.norm == "group":
        return nn.GroupNorm(max(1, min(8, channels // 4)), channels)
    return nn.Identity()


def conv(options: NetworkOptions, cin: int, cout: int, kernel: int = 3, dilation: int = 1, stride: int = 1) -> nn.Sequential:
    """Convolution → normalisation → activation, "same" padding for odd kernels."""
    pad = dilation * (kernel - 1) // 2
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=pad, dilation=dilation, bias=options.norm == "none"), _norm(options, cout), _activation(options)
    )


class _PoolToGrid(nn.Module):
    """Max-pools (2×2, ceil mode) a feature map of known size until both sides are at most `grid`."""

    def __init__(self, size: tuple[int, int], grid: int):
        super().__init__()
        h, w = size
        self.pools = 0
        while h > grid or w > grid:
            h, w = math.ceil(h / 2), math.ceil(w / 2)
            self.pools += 1
        self.out_size = (h, w)

    def forward(self, x: Tensor) -> Tensor:
        for _ in range(self.pools):
            x = F.max_pool2d(x, 2, ceil_mode=True)
        return x


def _fc_input(module: nn.Module, channels: int, size: tuple[int, int], grid: int) -> tuple[_PoolToGrid, int]:
    """The pooling to the grid for `module`'s output and the flattened size after it."""
    with torch.no_grad():
        was = module.training
        module.eval()
        out = module(torch.zeros(1, channels, *size))
        module.train(was)
    pool = _PoolToGrid((out.shape[2], out.shape[3]), grid)
    return pool, out.shape[1] * pool.out_size[0] * pool.out_size[1]


class PoseNetwork(nn.Module):
    """What every pose network shares: its options, the input check, the output scaling
    and the camera it was trained for."""

    name = "base"
    out_mean: Tensor
    out_std: Tensor
    camera: Tensor

    def __init__(self, options: NetworkOptions):
        super().__init__()
        self.options = options
        self.K = options.num_keypoints
        self.R = options.num_robots
        self.register_buffer("out_mean", torch.tensor([0.0, 0.0, 2.0]))
        self.register_buffer("out_std", torch.tensor([0.5, 0.5, 0.5]))
        w, h = options.input_size
        # (fx, fy, cx, cy) at the input size; a Kinect V2-like lens by default.
        self.register_buffer("camera", torch.tensor([w * 365.0 / 512.0, w * 365.0 / 512.0, (w - 1) / 2.0, (h - 1) / 2.0]))

    def set_output_statistics(self, mean: Tensor, std: Tensor) -> None:
        """The per-axis mean and spread of the training keypoints (metres)."""
        mean, std = torch.as_tensor(mean, dtype=torch.float32).reshape(3), torch.as_tensor(std, dtype=torch.float32).reshape(3)
        if not (torch.isfinite(mean).all() and torch.isfinite(std).all() and (std > 0).all()):
            raise ValueError(f"output statistics must be finite with std > 0, got mean {mean.tolist()}, std {std.tolist()}")
        self.out_mean.copy_(mean)
        self.out_std.copy_(std)

    def set_camera(self, intrinsics: Tensor) -> None:
        """The intrinsics (3, 3) at the input size that the training images share (nominally)."""
        k = torch.as_tensor(intrinsics, dtype=torch.float32)
        if k.shape != (3, 3) or not torch.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError(f"intrinsics must be a finite (3, 3) matrix with positive focal lengths, got {k.tolist()}")
        self.camera.copy_(torch.stack([k[0, 0], k[1, 1], k[0, 2], k[1, 2]]))

    def intrinsics(self) -> Tensor:
        fx, fy, cx, cy = self.camera.tolist()
        return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def check(self, image: Tensor) -> Tensor:
        if image.dim() != 4 or image.shape[1] != 3:
            raise ValueError(f"the network takes images (N, 3, H, W), got shape {tuple(image.shape)}")
        w, h = self.options.input_size
        if image.shape[2] != h or image.shape[3] != w:
            raise ValueError(f"this network was built for {w}×{h} images, got {image.shape[3]}×{image.shape[2]}")
        return (image - 0.5) / 0.25

    def points(self, raw: Tensor) -> Tensor:
        """Standardised (..., 3) → metres."""
        return raw * self.out_std + self.out_mean

    def upsample(self, logits: Tensor) -> Tensor:
        w, h = self.options.input_size
        if logits.shape[2] == h and logits.shape[3] == w:
            return logits
        return F.interpolate(logits, size=(h, w), mode="bilinear", align_corners=False)


def _head(options: NetworkOptions, features: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(features, options.head), _activation(options), nn.Linear(options.head, out))


class MultiObjectiveNet(PoseNetwork):
    """Paper V (Fig. 3, the digest's reconstruction): a shared first convolution (32, 3×3,
    dilation 2); the red mask branch (32-filter 3×3 convolutions, dilations 5, 3, 5, 3,
    then a 1-filter convolution); the blue branch (max-pool, Conv 64 3×3 d5, max-pool,
    Conv 128 2×2 d3, max-pool, FC `fc`); the green branch from the 4th convolution of the
    mask path (counting the shared one), pooled, into an FC `fc` summed with the blue
    one; three heads of FC `head`: keypoints 3·K, type R, base 3."""

    name = "multi"

    def __init__(self, options: NetworkOptions):
        super().__init__(options)
        o = options
        c32, c64, c128 = o.channels(32), o.channels(64), o.channels(128)
        w, h = o.input_size
        self.trunk = conv(o, 3, c32, 3, 2, stride=o.mask_stride)
        size = (math.ceil(h / o.mask_stride), math.ceil(w / o.mask_stride))
        dil = o.mask_dilations
        self.red_a = nn.Sequential(*[conv(o, c32, c32, 3, d) for d in dil[:2]])  # conv 2, 3 of the mask path
        self.red_b = nn.Sequential(*[conv(o, c32, c32, 3, d) for d in dil[2:]])  # conv 4.. of the mask path
        self.mask_out = nn.Conv2d(c32, 1, 3, padding=1)
        self.blue = nn.Sequential(
            nn.MaxPool2d(2, ceil_mode=True), conv(o, c32, c64, 3, 5), nn.MaxPool2d(2, ceil_mode=True), conv(o, c64, c128, 2, 3), nn.MaxPool2d(2, ceil_mode=True)
        )
        self.blue_pool, blue_n = _fc_input(self.blue, c32, size, o.grid)
        # The 4th convolution of the mask path is the first of red_b (or the last one if the path is shorter).
        self.green_from_b = len(dil) > 2
        self.green = nn.MaxPool2d(2, ceil_mode=True)
        self.green_pool, green_n = _fc_input(self.green, c32, size, o.grid)
        self.blue_fc = nn.Linear(blue_n, o.fc)
        self.green_fc = nn.Linear(green_n, o.fc)
        self.act = _activation(o)
        self.joints_head = _head(o, o.fc, 3 * o.num_keypoints)
        self.type_head = _head(o, o.fc, o.num_robots)
        self.base_head = _head(o, o.fc, 3)

    def forward(self, image: Tensor, mask: Tensor | None = None, intrinsics: Tensor | None = None) -> dict[str, Tensor]:
        x = self.trunk(self.check(image))
        a = self.red_a(x)
        if self.green_from_b:
            fourth = self.red_b[0](a)
            b = self.red_b[1:](fourth)
        else:
            fourth = b = a
        mask_logits = self.upsample(self.mask_out(b))
        blue = self.blue_pool(self.blue(x)).flatten(1)
        green = self.green_pool(self.green(fourth)).flatten(1)
        shared = self.act(self.blue_fc(blue) + self.green_fc(green))
        n = image.shape[0]
        return {
            "mask_logits": mask_logits,
            "keypoints": self.points(self.joints_head(shared).view(n, self.K, 3)),
            "base": self.points(self.base_head(shared)),
            "type_logits": self.type_head(shared),
        }


class CascadeNet(PoseNetwork):
    """Paper IV: a mask CNN (32-filter 3×3 convolutions, dilation 2 then `mask_dilations`
    (4 + 1 layers with the default's first three: 2, 5, 3, 5), a 1-filter convolution),
    then a joint CNN on the image multiplied by the mask (Conv 32 3×3 d2, max-pool,
    Conv 64 3×3 d5, max-pool, Conv 128 2×2 d3, FC `fc` (Paper IV: 500), 3·K keypoints
    plus the base's 3). The joint CNN sees the mask detached, so the two are trained as
    the paper trained them, separately, in one run; given a `mask` (the ground truth,
    as the paper's "separate" evaluation) it uses that instead of its own."""

    name = "cascade"

    def __init__(self, options: NetworkOptions):
        super().__init__(options)
        o = options
        c32, c64, c128 = o.channels(32), o.channels(64), o.channels(128)
        w, h = o.input_size
        dil = [2, *o.mask_dilations[:3]]
        self.mask_net = nn.Sequential(conv(o, 3, c32, 3, dil[0], stride=o.mask_stride), *[conv(o, c32, c32, 3, d) for d in dil[1:]], nn.Conv2d(c32, 1, 3, padding=1))
        self.joint_net = nn.Sequential(
            conv(o, 3, c32, 3, 2), nn.MaxPool2d(2, ceil_mode=True), conv(o, c32, c64, 3, 5), nn.MaxPool2d(2, ceil_mode=True), conv(o, c64, c128, 2, 3)
        )
        self.pool, n = _fc_input(self.joint_net, 3, (h, w), o.grid)
        self.fc = nn.Sequential(nn.Linear(n, o.fc), _activation(o), nn.Linear(o.fc, 3 * o.num_keypoints + 3))

    def forward(self, image: Tensor, mask: Tensor | None = None, intrinsics: Tensor | None = None) -> dict[str, Tensor]:
        x = self.check(image)
        mask_logits = self.upsample(self.mask_net(x))
        weight = torch.sigmoid(mask_logits).detach() if mask is None else mask.to(image.dtype)
        masked = self.check(image * weight)
        out = self.fc(self.pool(self.joint_net(masked)).flatten(1))
        n = image.shape[0]
        return {
            "mask_logits": mask_logits,
            "keypoints": self.points(out[:, : 3 * self.K].view(n, self.K, 3)),
            "base": self.points(out[:, 3 * self.K :]),
        }


def _regrid(x: Tensor, size: tuple[int, int], factor: int) -> Tensor:
    """`x` on the grid of a map `factor` times finer (2, 4, ...) or, for a negative
    `factor`, -factor times coarser, of `size` (h, w). The grids are those of strided
    3×3 convolutions with "same" padding: cell j of a stride-s map is centred on input
    pixel s·j (not s·j + (s-1)/2), so a finer cell j lies at this map's j / factor
    (bilinear, corner-aligned; the last row and column repeated where the finer map
    reaches beyond) and a coarser cell j at this map's -factor·j."""
    h, w = size
    if factor < 0:
        y = x[:, :, ::-factor, ::-factor]
    elif factor > 1:
        hin, win = x.shape[2], x.shape[3]
        y = F.interpolate(x, size=((hin - 1) * factor + 1, (win - 1) * factor + 1), mode="bilinear", align_corners=True)
    else:
        y = x
    y = y[:, :, :h, :w]
    if y.shape[2] < h or y.shape[3] < w:
        y = F.pad(y, (0, w - y.shape[3], 0, h - y.shape[2]), mode="replicate")
    return y


def cell_centres(count: int, stride: int, dtype: torch.dtype = torch.float32, device: torch.device | None = None) -> Tensor:
    """Input-pixel coordinates (pixel centres at integers) of the cells of a stride-`stride`
    map made by strided 3×3 convolutions with "same" padding: s·j (`_regrid`)."""
    return torch.arange(count, dtype=dtype, device=device) * float(stride)


class KeypointNet(PoseNetwork):
    """Beyond the papers: 2D heatmaps (K keypoints + the base) with a depth per keypoint,
    at `heatmap_stride`. Pixels are the heatmaps' soft-argmax (their expected position),
    depths the heatmap-weighted mean of each keypoint's depth map (log-depth around the
    training mean), and the 3D keypoints the pixels back-projected at those depths
    through the intrinsics (the network's own, `set_camera`, or per image). An encoder of
    strided and dilated convolutions to 1/8 with a coarse-to-fine merge at the heatmap
    stride; the mask at 1/2 from the stem's and the merged features, upsampled; the type
    from pooled features."""

    name = "keypoint"

    def __init__(self, options: NetworkOptions):
        super().__init__(options)
        o = options
        c32, c64, c128 = o.channels(32), o.channels(64), o.channels(128)
        s = o.heatmap_stride
        self.stem = nn.Sequential(conv(o, 3, c32, 3, 1, stride=2), conv(o, c32, c32, 3, 2))  # 1/2
        self.down4 = nn.Sequential(conv(o, c32, c64, 3, 1, stride=2), conv(o, c64, c64, 3, 2), conv(o, c64, c64, 3, 5))  # 1/4
        self.down8 = nn.Sequential(conv(o, c64, c128, 3, 1, stride=2), conv(o, c128, c128, 3, 2), conv(o, c128, c128, 3, 4))  # 1/8
        self.merge = nn.Sequential(conv(o, c64 + c128, c64, 1), conv(o, c64, c64, 3, 1))
        self.stride = s
        k1 = o.num_keypoints + 1
        self.heat = nn.Conv2d(c64, k1, 1)
        self.depth = nn.Conv2d(c64, k1, 1)
        # The mask at 1/2 from the stem's features and the merged ones (thin links vanish at 1/4).
        self.mask_out = nn.Sequential(conv(o, c32 + c64, c32, 3, 1), nn.Conv2d(c32, 1, 3, padding=1))
        self.type_head = nn.Sequential(nn.Linear(c128, o.head), _activation(o), nn.Linear(o.head, o.num_robots))

    def _features(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        half = self.stem(x)
        quarter = self.down4(half)
        eighth = self.down8(quarter)
        target = {2: half, 4: quarter, 8: eighth}[self.stride]
        up8 = _regrid(eighth, (quarter.shape[2], quarter.shape[3]), 2)
        fine = self.merge(torch.cat([quarter, up8], 1))
        if target is not quarter:
            fine = _regrid(fine, (target.shape[2], target.shape[3]), 2 if self.stride == 2 else -2)
        return fine, eighth, half

    def forward(self, image: Tensor, mask: Tensor | None = None, intrinsics: Tensor | None = None) -> dict[str, Tensor]:
        x = self.check(image)
        n = image.shape[0]
        fine, coarse, half = self._features(x)
        hh, ww = fine.shape[2], fine.shape[3]
        heat = self.heat(fine).flatten(2)  # (N, K+1, hh·ww)
        prob = torch.softmax(heat, dim=2)
        # Heatmap cell centres in input pixels (OpenCV convention: pixel centres at
        # integers): cell j of the stride-s map is centred on input pixel s·j.
        ys = cell_centres(hh, self.stride, image.dtype, image.device)
        xs = cell_centres(ww, self.stride, image.dtype, image.device)
        gy = ys.view(hh, 1).expand(hh, ww).reshape(-1)
        gx = xs.view(1, ww).expand(hh, ww).reshape(-1)
        u = (prob * gx).sum(2)
        v = (prob * gy).sum(2)
        log_z = (prob * self.depth(fine).flatten(2)).sum(2)
        z = torch.exp(torch.log(self.out_mean[2].clamp(min=0.1)) + log_z * (self.out_std[2] / self.out_mean[2].clamp(min=0.1)))
        if intrinsics is None:
            fx, fy, cx, cy = self.camera[0], self.camera[1], self.camera[2], self.camera[3]
        else:
            fx, fy = intrinsics[:, 0, 0:1], intrinsics[:, 1, 1:2]
            cx, cy = intrinsics[:, 0, 2:3], intrinsics[:, 1, 2:3]
            if self.options.zoom > 1:
                # A box zoomed s times shows the robot as the network's camera would at
                # depth z / s: the network gives that depth, the focal lengths the rest
                # (the rule `earcore.pose.estimate` applies to any camera).
                z = z * torch.sqrt(fx * fy / (self.camera[0] * self.camera[1]))
        points = torch.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], dim=2)
        pooled = coarse.mean(dim=(2, 3))
        return {
            "mask_logits": self.upsample(self.mask_out(torch.cat([half, F.interpolate(fine, size=half.shape[2:], mode="bilinear", align_corners=False)], 1))),
            "keypoints": points[:, : self.K],
            "base": points[:, self.K],
            "type_logits": self.type_head(pooled),
            "pixels": torch.stack([u, v], dim=2).view(n, self.K + 1, 2),
        }


_CLASSES: dict[str, type[PoseNetwork]] = {"multi": MultiObjectiveNet, "cascade": CascadeNet, "keypoint": KeypointNet}


def build_network(name: str, options: NetworkOptions | dict[str, Any] | None = None, *, preset: str | None = None) -> PoseNetwork:
    """A network by name ("multi", "cascade", "keypoint") with `options` (a preset's
    values, then the given ones, over the defaults)."""
    if name not in _CLASSES:
        raise ConfigError(f"network must be one of {', '.join(NETWORKS)}, got {name!r}")
    if not isinstance(options, NetworkOptions):
        values: dict[str, Any] = {}
        if preset is not None:
            if preset not in PRESETS:
                raise ConfigError(f"preset must be one of {', '.join(PRESETS)}, got {preset!r}")
            values.update(PRESETS[preset])
        values.update(options or {})
        if name == "cascade" and "fc" not in (options or {}) and preset in (None, "paper"):
            values["fc"] = 500  # Paper IV's FC 500
        options = NetworkOptions.from_dict(values)
    if name != "keypoint" and options.zoom != 1:
        raise ConfigError(f"zoom is for the keypoint network (its depths follow each box's focal length); the {name} network regresses 3D from the whole image")
    return _CLASSES[name](options)
