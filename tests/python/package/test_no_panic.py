"""No public call of the compiled module can panic or take the process down.

Every public function, method and property setter of ``earcore._earcore`` (enumerated
from the module, so a new one is covered or this test fails) is driven with random
shapes, dtypes, layouts, sizes and extreme values, in child processes. A child fails
on an exit by signal (abort, segfault), on a ``pyo3_runtime.PanicException`` (a
BaseException that ``except Exception`` misses) or on a timeout. Cases are seeded; a
failure names the call and the command that replays it alone:

    python tests/python/package/test_no_panic.py CASE
"""

from __future__ import annotations

import inspect
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

SEED = 36
BATCHES = 8
PER_BATCH = 300
HERE = Path(__file__).resolve()

# Panics in code another change owns: (callable, what reproduces it). The child reports
# them as known instead of failing; `test_known_panics_still_reproduce` keeps each one
# honest (it fails once the panic is fixed, so the entry gets removed).
KNOWN_PANICS: dict[str, str] = {}


# --- the child: build base objects, generate and run cases -------------------------------

#: Parameter name → the kind of value it takes (every parameter of every public callable
#: must be listed: `test_every_parameter_has_a_kind` checks it).
KINDS = {
    **dict.fromkeys(
        ["points", "origins", "directions", "centres", "vertices", "src", "dst", "source", "normals"], "points"
    ),
    **dict.fromkeys(
        ["sensor_origin", "origin", "direction", "point", "center", "box_min", "box_max", "bbx_min", "bbx_max",
         "viewpoint"],
        "vec3",
    ),
    **dict.fromkeys(["base_from_camera", "base_from_sensor", "initial", "base", "matrix"], "pose"),
    **dict.fromkeys(["q", "qs", "q0", "q1", "q0s", "q1s", "path", "last", "now", "ahead", "command", "reference"], "q"),
    **dict.fromkeys(["lower", "upper", "max_velocity", "max_acceleration"], "q"),
    **dict.fromkeys(
        ["resolution", "max_range", "value", "delta", "dt", "size", "margin", "padding", "cell", "voxel_size",
         "radius", "threshold", "fx", "fy", "cx", "cy", "depth_scale", "min_depth", "max_depth", "floor_z", "gain",
         "tolerance", "std_ratio", "max_correspondence_distance", "translation_tolerance", "rotation_tolerance", "sigma_tolerance",
         "huber_delta", "prob_hit", "prob_miss", "clamping_min", "clamping_max", "occupancy_threshold",
         "danger_alpha", "similar", "beam_spacing", "max_leaf_size", "vertical_fov_deg", "noise_sigma",
         "index_margin", "near", "far", "ambient", "diffuse", "edge"],
        "float",
    ),
    **dict.fromkeys(
        ["depth", "k", "repeat", "link", "iterations", "seed", "rings", "azimuth_steps", "width", "height",
         "max_iterations", "n", "position_memory", "source_width", "source_height"],
        "int",
    ),
    **dict.fromkeys(
        ["discretize", "ignore_unknown", "occupied", "occupied_only", "leaves_only", "self_collision",
         "return_links", "adaptive_huber"],
        "bool",
    ),
    "update": "update",
    "obstacles": "obstacles",
    "shape": "shape",
    "decay_mode": "decay_mode",
    "tree": "tree",
    "target": "target",
    "spheres": "spheres",
    "boxes": "boxes",
    "depth_image": "depth_image",
    "distortion": "numbers",
    "values": "values",
    "weights": "weights",
    "self_collision_pairs": "pairs",
    "_memo": "memo",
    "link_names": "robot_part",
    "joints": "robot_part",
    "bodies": "robot_part",
    "name": "name",
    "meshes": "meshes",
    "camera_from_mesh": "mesh_poses",
    "hidden": "flags",
    "light": "vec3",
    "background": "rgb_bytes",
    "u": "image2d",
    "v": "image2d",
}

#: Parameters whose meaning depends on the callable.
OVERRIDES = {
    ("depth_to_points_raw", "depth"): "depth_image",
    ("incidence_cosines", "depth"): "depth_image",
    ("PixelMap.depth", "depth"): "depth_image",
    ("PixelMap.bilinear", "image"): "image_u8",
    ("PixelMap.nearest", "image"): "labels",
    ("OcTree.read", "path"): "file",
    ("OcTree.read_binary", "path"): "file",
    ("OcTree.write", "path"): "file",
    ("OcTree.write_binary", "path"): "file",
    ("RobotModel.path_danger", "path"): "q",
    ("RobotModel.bodies", "q"): "q",
}

SETTABLE = {
    "OcTree": ["danger_alpha", "decay_mode"],
    "RobotModel": ["base", "index_margin", "self_collision_pairs"],
}


def public_callables(ec):
    """(name, owner class or None, attribute) of every public callable of the module."""
    out = []
    for name in sorted(dir(ec)):
        obj = getattr(ec, name)
        if name.startswith("_") or not callable(obj):
            continue
        if inspect.isclass(obj):
            if issubclass(obj, BaseException):
                continue
            out.append((name, None, name))
            for attr in sorted(dir(obj)):
                if attr.startswith("_") and attr not in ("__len__", "__copy__", "__deepcopy__"):
                    continue
                raw = inspect.getattr_static(obj, attr)
                if type(raw).__name__ in ("getset_descriptor", "member_descriptor", "property"):
                    continue
                out.append((f"{name}.{attr}", name, attr))
            for attr in SETTABLE.get(name, []):
                out.append((f"{name}.{attr}=", name, attr))
        else:
            out.append((name, None, name))
    return out


def parameters(ec, qualname, owner, attr):
    """[(name, kind, required)] of a callable's parameters (self excluded)."""
    if qualname.endswith("="):
        return [(attr, KINDS[attr], True)]
    obj = getattr(ec, owner) if owner else ec
    fn = getattr(obj, attr) if owner else getattr(ec, attr)
    params = []
    for p in inspect.signature(fn).parameters.values():
        if p.name == "self":
            continue
        kind = OVERRIDES.get((qualname, p.name)) or KINDS.get(p.name)
        params.append((p.name, kind, p.default is inspect.Parameter.empty))
    return params


class Generator:
    """Hostile and valid arguments, drawn from one seeded generator per case."""

    def __init__(self, rng, ec, scratch, dof):
        self.rng, self.ec, self.scratch, self.dof = rng, ec, scratch, dof

    def pick(self, options):
        return options[int(self.rng.integers(len(options)))]

    def extreme(self):
        return self.pick([0.0, -0.0, np.inf, -np.inf, np.nan, 1e308, -1e308, 1e-308, 5e-324, 1e20, -1.0, 2.0**63])

    def bad_number(self):
        """A number at or past the edge of what a size, count or length can be."""
        if self.rng.integers(4) == 0:
            return self.bad_scalar()
        return self.pick([
            0, -1, 2**31, 2**32 + 1, 2**53, 2**62, 2**63 - 1, 2**63, 2**64 - 1, -(2**63), 255, 65536,
            0.0, -0.0, np.inf, -np.inf, np.nan, 1e308, -1e308, 1e-308, 5e-324, 1e-12, 1e12, -1e-9,
        ])

    def bad_scalar(self):
        return self.pick([
            None, "x", b"x", [], [1.0, 2.0], {}, object(), 1 + 1j, np.complex128(1j), True, np.False_,
            2**63, -(2**63) - 1, 2**64, 10**30, -1, 0, np.int8(-1), np.uint64(2**64 - 1), np.float16(6e4),
            np.array([1.0]), np.zeros((0,)), np.nan, np.inf, 1e308, -1e308, 5e-324,
        ])

    def mutate_array(self, a):
        """The valid array `a`, changed in one hostile way (or returned as it is)."""
        rng = self.rng
        how = int(rng.integers(25))
        a = np.asarray(a)
        if how == 0:
            return a.astype(self.pick([np.bool_, np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint64,
                                       np.float16, np.float32]))
        if how == 1:
            return a.astype(np.complex128) + 1j
        if how == 2:
            return a.astype(object)
        if how == 3:
            return a.astype(str)
        if how == 4:
            return np.asfortranarray(a)
        if how == 5 and a.ndim:
            return np.repeat(a, 2, axis=0)[::2]
        if how == 6 and a.ndim:
            return a[::-1]
        if how == 7:
            # Misaligned but contiguous float64: a view one byte into a buffer.
            buf = np.zeros(a.size * 8 + 1, np.uint8)
            v = buf[1:].view(np.float64).reshape(a.shape)
            v[...] = a.astype(np.float64, copy=False) if a.dtype.kind in "fiub" else 0.0
            return v
        if how == 8:
            b = np.array(a)
            b.flags.writeable = False
            return b
        if how == 9 and a.size:
            b = np.array(a, dtype=np.float64)
            b.flat[int(rng.integers(b.size))] = self.extreme()
            return b
        if how == 10 and a.size:
            return np.full(a.shape, self.extreme())
        if how == 11 and a.ndim:
            return a[:0]
        if how == 12 and a.ndim:
            return a[:1]
        if how == 13:
            return np.asarray(5.0)
        if how == 14:
            return a.reshape(a.shape + (1,))
        if how == 15 and a.ndim == 2:
            return np.zeros((a.shape[0], self.pick([0, 1, 2, 4, 7])))
        if how == 16:
            return np.ma.masked_array(a, mask=np.ones(a.shape, bool))
        if how == 17:
            return a.tolist()
        if how == 18 and a.size:
            return np.full(a.shape, self.pick([2**62, -(2**62), 2**63 - 1]), dtype=np.int64)
        if how == 19:
            return np.zeros((int(rng.integers(1, 3000)),) + a.shape[1:])
        if how == 20:
            return self.bad_scalar()
        if how == 21 and a.ndim:
            return np.swapaxes(np.atleast_2d(a), 0, -1)
        if how == 23 and a.ndim == 2:
            # A broadcast view: tiny in memory, enormous if copied.
            return np.broadcast_to(np.zeros(1, a.dtype), (2**21, 2**21))
        if how == 22 and a.size:
            return a.astype(np.float64) * self.pick([1e300, 1e-300, -1e10, 1e10])
        return a

    def valid(self, kind):
        rng, dof = self.rng, self.dof
        n = self.pick([0, 1, 2, 5, 40])
        if kind == "points":
            return rng.normal(0.0, 0.5, (n, 3))
        if kind == "vec3":
            return rng.normal(0.0, 0.3, 3)
        if kind == "pose":
            return np.eye(4)
        if kind == "q":
            return rng.uniform(-0.5, 0.5, self.pick([(dof,), (n, dof)]))
        if kind == "float":
            return float(self.pick([0.01, 0.05, 0.1, 0.5, 1.0, 0.3]))
        if kind == "int":
            return int(self.pick([0, 1, 2, 3, 8, 20]))
        if kind == "bool":
            return bool(rng.integers(2))
        if kind == "update":
            return self.pick([True, False, 0.5, -0.4])
        if kind == "obstacles":
            return self.pick(["occupied", "current"])
        if kind == "shape":
            return self.pick(["capsule", "cylinder", "auto"])
        if kind == "decay_mode":
            return self.pick(["observed", "always"])
        if kind == "tree":
            return self.tree()
        if kind == "target":
            if rng.integers(2):
                return self.ec.PlaneTarget(rng.normal(0, 1, (30, 3)), np.tile([0.0, 0.0, 1.0], (30, 1)))
            return _surface(self.ec, rng)
        if kind == "spheres":
            return np.array([[0.0, 0.0, 2.0, 0.5]])[: self.pick([0, 1])]
        if kind == "boxes":
            return np.array([[-3.0, -3.0, -1.0, 3.0, 3.0, 4.0]])[: self.pick([0, 1])]
        if kind == "depth_image":
            return rng.uniform(0.5, 3.0, (self.pick([0, 1, 4, 8]), self.pick([0, 1, 4, 8])))
        if kind == "numbers":
            return rng.normal(0, 0.01, self.pick([0, 4, 5, 8]))
        if kind in ("values", "weights"):
            return rng.uniform(0, 1, self.pick([(n,), (n, 2)]))
        if kind == "pairs":
            return [(int(rng.integers(12)), int(rng.integers(12))) for _ in range(self.pick([0, 1, 3]))]
        if kind == "memo":
            return {}
        if kind == "file":
            return self.file()
        if kind == "name":
            return self.pick([None, "r", "é" * 3])
        if kind == "meshes":
            vertices = rng.normal(0.0, 1.0, (self.pick([0, 3, 8]), 3)) + [0.0, 0.0, 3.0]
            triangles = rng.integers(0, max(len(vertices), 1), (self.pick([0, 1, 12]), 3))
            return [(vertices, triangles, (0.5, 0.5, 0.5), int(rng.integers(-1, 9))) for _ in range(self.pick([0, 1, 2]))]
        if kind == "mesh_poses":
            return np.tile(np.eye(4), (self.pick([0, 1, 2]), 1, 1))
        if kind == "flags":
            return [bool(b) for b in rng.integers(0, 2, self.pick([0, 1, 2]))]
        if kind == "rgb_bytes":
            return self.pick([(0, 0, 0), (255, 255, 255), (256, 0, 0), (-1, 0, 0), (1, 2)])
        if kind == "image2d":
            return rng.uniform(-2.0, 10.0, (self.pick([0, 1, 4]), self.pick([0, 1, 4])))
        if kind == "image_u8":
            return rng.integers(0, 256, (self.pick([0, 4, 8]), self.pick([0, 4, 8]), self.pick([0, 1, 3]))).astype(np.uint8)
        if kind == "labels":
            return rng.integers(-1, 9, (self.pick([0, 4, 8]), self.pick([0, 4, 8])))
        raise AssertionError(f"no generator for kind {kind!r}")

    def tree(self):
        t = self.ec.OcTree(self.pick([0.05, 0.1, 0.02]))
        t.insert_point_cloud(self.rng.normal(0.0, 0.6, (200, 3)) + [0.3, 0.0, 0.4], [0.0, 0.0, 0.0])
        t.end_frame(0.1)
        return t

    def file(self):
        d = self.scratch
        good = d / "good.ot"
        if not good.exists():
            self.tree().write(good)
            self.tree().write_binary(d / "good.bt")
        garbage = d / "garbage.ot"
        garbage.write_bytes(self.rng.bytes(int(self.rng.integers(0, 400))))
        trailing = d / "trailing.ot"
        trailing.write_bytes(good.read_bytes() + b"\0junk")
        cut = d / "cut.bt"
        data = (d / "good.bt").read_bytes()
        cut.write_bytes(data[: int(self.rng.integers(len(data)))])
        return self.pick([good, str(good), d / "good.bt", garbage, trailing, cut, d, d / "no" / "x.ot", "",
                          d / "out.ot", str(d / "out.bt"), 7, None, b"x"])

    def robot(self):
        """A robot built from random, often degenerate parts (None if refused)."""
        try:
            return self.ec.RobotModel(**self.robot_parts())
        except (ValueError, TypeError, OverflowError):
            return None

    def robot_parts(self):
        """Constructor arguments of a robot from random, often degenerate parts."""
        rng = self.rng
        links = int(self.pick([1, 2, 3, 5]))
        names = [f"l{i}" for i in range(links)]
        joints = []
        for c in range(1, links):
            kind = self.pick(["revolute", "continuous", "prismatic", "fixed", "fixed", "ball"])
            xyz = tuple(rng.normal(0, 0.3, 3)) if rng.integers(6) else (self.extreme(), 0.0, 0.0)
            axis = self.pick([(0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), (np.nan, 0.0, 1.0)])
            lo, hi = self.pick([(-1.0, 1.0), (0.0, 0.0), (1.0, -1.0), (-np.inf, np.inf), (-1e300, 1e300)])
            joints.append((f"j{c}", kind, int(rng.integers(c)), c, xyz, (0.0, 0.0, 0.0), axis, lo, hi))
        bodies = []
        for _ in range(links):
            if rng.integers(3) == 0:
                bodies.append(None)
                continue
            a = tuple(rng.normal(0, 0.2, 3))
            b = self.pick([a, tuple(rng.normal(0, 0.2, 3)), (0.0, 0.0, self.extreme()), (0.0, 0.0, 1e3)])
            r = self.pick([0.0, 0.05, self.extreme(), 1e3])
            bodies.append((a, b, r, self.pick(["capsule", "cylinder", "sphere"])))
        padding = self.pick([0.0, 0.01, self.extreme()])
        return dict(link_names=names, joints=joints, bodies=bodies, padding=padding)


def describe(v):
    if isinstance(v, np.ndarray):
        flags = "".join(f for f, on in [("C", v.flags.c_contiguous), ("F", v.flags.f_contiguous),
                                        ("A", v.flags.aligned), ("W", v.flags.writeable)] if on)
        # `flat` reads the first values without a copy (a broadcast view may be vast).
        head = [v.flat[i] for i in range(min(3, v.size))] if v.dtype != object else "objects"
        return f"{type(v).__name__}({v.dtype}, {v.shape}, flags={flags}, strides={v.strides}, head={head})"
    if isinstance(v, list) and len(v) > 4:
        return f"list(len={len(v)})"
    text = repr(v)
    return text if len(text) < 80 else text[:77] + "..."


def run_child(cases, verbose=False):
    """Run the given case numbers; one JSON line per case started and per problem."""
    import earcore.robots
    from earcore import _earcore as ec

    # The parent's folder, removed by the parent even when a case kills this process.
    given = os.environ.get("EARCORE_FUZZ_SCRATCH")
    scratch = Path(given) if given else Path(tempfile.mkdtemp(prefix="earcore-fuzz-"))
    os.chdir(scratch)
    ur5 = earcore.robots.load("ur5")
    toy = ec.RobotModel(
        ["base", "upper", "fore"],
        [("a", "revolute", 0, 1, (0, 0, 0.2), (0, 0, 0), (0, 0, 1), -3.0, 3.0),
         ("b", "prismatic", 1, 2, (0.3, 0, 0), (0, 0, 0), (1, 0, 0), -0.2, 0.2)],
        [None, ((0, 0, 0), (0.3, 0, 0), 0.04, "cylinder"), ((0, 0, 0), (0.2, 0, 0), 0.03, "capsule")],
    )
    callables = public_callables(ec)
    for i in cases:
        rng = np.random.default_rng([SEED, i])
        qualname, owner, attr = callables[i % len(callables)]
        robot = None
        if owner == "RobotModel":
            choice = int(rng.integers(4))
            gen = Generator(rng, ec, scratch, 0)
            robot = {0: ur5, 1: toy}.get(choice) or gen.robot() or toy
        dof = robot.dof if robot is not None else 6
        gen = Generator(rng, ec, scratch, dof)
        params = parameters(ec, qualname, owner, attr)
        args = gen.robot_parts() if qualname == "RobotModel" else {}
        for name, kind, required in params:
            if name in args:
                continue
            if not required and rng.integers(3) == 0:
                continue
            value = gen.valid(kind)
            if rng.integers(3) == 0:
                try:
                    if kind in ("float", "int"):
                        value = gen.bad_number()
                    elif kind in ("tree", "target", "memo"):
                        value = gen.bad_scalar()
                    else:
                        value = gen.mutate_array(value)
                except (ValueError, TypeError):
                    # Not every mutation applies to every value (strings cannot be complex).
                    value = gen.bad_scalar()
            args[name] = value
        target = {"OcTree": gen.tree, "SurfaceMap": lambda: _surface(ec, rng),
                  "PlaneTarget": lambda: ec.PlaneTarget(rng.normal(0, 1, (9, 3)), rng.normal(0, 1, (9, 3))),
                  "Follower": lambda: ec.Follower(np.ones(6), np.ones(6), 2.0),
                  "Rasterizer": lambda: ec.Rasterizer([(np.eye(3) + [0.0, 0.0, 2.0], [[0, 1, 2]], (1.0, 0.5, 0.0), 3)]),
                  "PixelMap": lambda: ec.PixelMap(4, 4, rng.uniform(-1, 5, (3, 5)), rng.uniform(-1, 5, (3, 5))),
                  "RobotModel": lambda: robot}.get(owner or "", lambda: None)()
        text = f"{qualname}({', '.join(f'{k}={describe(v)}' for k, v in args.items())})"
        print(json.dumps({"case": i, "call": text}), flush=True)
        outcome = "returned"
        try:
            if qualname.endswith("="):
                setattr(target, attr, args[attr])
            elif owner is None:
                getattr(ec, attr)(**args)
            elif attr in ("read", "read_binary"):
                getattr(ec.OcTree, attr)(**args)
            else:
                getattr(target, attr)(**args)
        except BaseException as exc:  # noqa: BLE001 - a PanicException is what we look for
            outcome = f"{type(exc).__name__}: {str(exc)[:200]}"
            if type(exc).__name__ == "PanicException" or not isinstance(exc, Exception):
                known = qualname in KNOWN_PANICS
                print(json.dumps({"case": i, "call": text, "panic": f"{type(exc).__name__}: {exc}",
                                  "known": known}), flush=True)
        finally:
            if verbose:
                print(f"  -> {outcome}", flush=True)
            ec.set_num_threads(0)
            ec.set_local_num_threads(None)
            ur5.base, ur5.index_margin = np.eye(4), 0.5
    print(json.dumps({"done": True}), flush=True)


def _surface(ec, rng):
    s = ec.SurfaceMap(0.05)
    s.insert(rng.normal(0, 1, (200, 3)))
    return s


# --- the tests ---------------------------------------------------------------------------


def _child(cases, timeout):
    cmd = [sys.executable, str(HERE), "--child", ",".join(map(str, cases))]
    with tempfile.TemporaryDirectory(prefix="earcore-fuzz-") as scratch:
        env = dict(os.environ, RUST_BACKTRACE="0", EARCORE_FUZZ_SCRATCH=scratch)
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
            out, code, timed_out = proc.stdout, proc.returncode, False
        except subprocess.TimeoutExpired as exc:
            raw = exc.stdout or b""
            out, code, timed_out = raw.decode() if isinstance(raw, bytes) else raw, None, True
            proc = None
    lines = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    return lines, code, timed_out, (proc.stderr[-2000:] if proc else "")


def _replay(case):
    return f"replay: {sys.executable} {HERE.relative_to(Path.cwd()) if HERE.is_relative_to(Path.cwd()) else HERE} {case}"


@pytest.mark.parametrize("batch", range(BATCHES))
def test_no_public_call_panics_or_aborts(batch):
    cases = list(range(batch * PER_BATCH, (batch + 1) * PER_BATCH))
    lines, code, timed_out, stderr = _child(cases, timeout=150)
    started = [entry for entry in lines if "call" in entry and "panic" not in entry]
    last = started[-1] if started else {"case": None, "call": "(before the first case)"}
    assert not timed_out, f"timed out in case {last['case']}: {last['call']}\n{_replay(last['case'])}"
    assert code == 0 and lines and lines[-1].get("done"), (
        f"the child died (exit {code}) in case {last['case']}: {last['call']}\n{_replay(last['case'])}\n{stderr}"
    )
    panics = [e for e in lines if "panic" in e and not e["known"]]
    assert not panics, "\n".join(f"case {e['case']}: {e['call']} -> {e['panic']}\n{_replay(e['case'])}"
                                 for e in panics)
    # The batch covered what it was meant to (a silent early exit would pass the above).
    assert len(started) + sum("panic" in e for e in lines) >= PER_BATCH


def test_every_public_callable_is_driven():
    from earcore import _earcore as ec

    callables = public_callables(ec)
    names = {q for q, _, _ in callables}
    # Spot checks that the enumeration sees functions, classes, methods and setters.
    for expected in ["voxel_codes", "OcTree", "OcTree.insert_point_cloud", "RobotModel.motion_danger",
                     "RobotModel.base=", "Follower.rollout", "SurfaceMap.associate", "fit_body"]:
        assert expected in names
    # Each batch walks the list in order, so every callable is met in every batch.
    assert PER_BATCH >= len(callables)


def test_every_parameter_has_a_kind():
    from earcore import _earcore as ec

    missing = [(q, n) for q, owner, attr in public_callables(ec) for n, kind, _ in parameters(ec, q, owner, attr)
               if kind is None]
    assert not missing, f"parameters without a generator: {missing}"


@pytest.mark.parametrize(
    "call",
    [
        lambda ec: ec.render_depth_points(np.eye(4), [], [], width=2**40, height=2**40),
        lambda ec: ec.render_depth_points(np.eye(4), [], [], width=2**20, height=2**20),
        lambda ec: ec.render_depth_points(np.eye(4), [], [], max_depth=np.inf),
        lambda ec: ec.render_depth_points(np.eye(4), [], [], cx=np.nan),
        lambda ec: ec.render_lidar_scan(np.eye(4), [], [], rings=2**40, azimuth_steps=2**40),
        lambda ec: ec.render_lidar_scan(np.eye(4), [], [], rings=2**13, azimuth_steps=2**13),
        lambda ec: ec.render_lidar_scan(np.eye(4), [], [], max_range=np.inf),
    ],
)
def test_synthetic_frame_sizes_are_bounded(call):
    # Sizes multiply before anything is cast: once a capacity overflow (panic) or an
    # allocation the process could not survive.
    from earcore import _earcore as ec

    with pytest.raises(ValueError, match="rings|width|max_depth|max_range|cx"):
        call(ec)
    # In bounds, the same calls render: a room around a lidar gives one point per beam.
    room = [[-3.0, -3.0, -3.0, 3.0, 3.0, 3.0]]
    assert ec.render_lidar_scan(np.eye(4), [], room, rings=4, azimuth_steps=90, noise_sigma=0.0).shape == (360, 3)


@pytest.mark.parametrize("name", sorted(KNOWN_PANICS))
@pytest.mark.xfail(strict=True, reason="a panic in code owned elsewhere (see KNOWN_PANICS)")
def test_known_panics_still_reproduce(name):
    code = KNOWN_PANICS[name]
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, RUST_BACKTRACE="0"))
    assert proc.returncode == 0 and "PanicException" not in proc.stderr, proc.stderr[-500:]


if __name__ == "__main__":
    if sys.argv[1] == "--child":
        run_child([int(c) for c in sys.argv[2].split(",")])
    else:
        # Replay one case in the foreground, printing the call and its outcome.
        run_child([int(c) for c in sys.argv[1:]], verbose=True)
