"""`earcore dataset robots`: labelled robot images from the simulator ("earcore-images"
format, docs/robot-images.md).

    earcore dataset robots --out data/robots                        # the papers' UR set (4,350 images)
    earcore dataset robots --out data/kuka --robots iiwa,panda --scale 0.5
    earcore dataset robots --out data/random --mode random --count 2000 --workers 2
    earcore dataset robots --out data/robots --ray                  # tasks on a Ray cluster

Rerunning the same command completes the missing shards (an interrupted run resumes);
a folder made with other options is refused. `--ray` connects to the cluster at
`--ray-address` ("auto": the one this machine belongs to, e.g. started by `ray start`);
when there is none, a local Ray instance is started (`ray.init()`).
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from earcore.app.arguments import Parser, count, fail, positive, positive_int

__all__ = ["main"]

PROG = "earcore dataset robots"


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 128x106, got {text!r}") from None
    if not (16 <= w <= 2048 and 16 <= h <= 2048):
        raise argparse.ArgumentTypeError(f"width and height must be in [16, 2048], got {text!r}")
    return w, h


def _parser() -> Parser:
    parser = Parser(prog="earcore dataset", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", choices=["robots", "parts"], help="what to generate (robots: robot pose images; parts: see `earcore dataset parts --help`)")
    parser.add_argument("--out", type=Path, required=True, help="the dataset folder (created; resumed if it exists)")
    parser.add_argument("--robots", default="ur3,ur5,ur10", help="comma-separated, class order (default ur3,ur5,ur10; also iiwa, panda)")
    parser.add_argument(
        "--mode",
        choices=["recordings", "random"],
        default="recordings",
        help="recordings: a fixed camera per recording while the joints sweep (the papers); random: a new camera per image",
    )
    sizes = parser.add_mutually_exclusive_group()
    sizes.add_argument("--scale", type=positive, default=None, help="the papers' recording sizes times this (default 1)")
    sizes.add_argument("--count", type=positive_int, default=None, help="images per robot instead")
    parser.add_argument("--size", type=_size, default=(128, 106), help="image WIDTHxHEIGHT (default 128x106, the papers' 512x424 / 4)")
    parser.add_argument("--seed", type=count, default=0)
    parser.add_argument("--meshes", choices=["visual", "collision"], default="visual", help="robot meshes rendered (collision: coarser, faster)")
    parser.add_argument("--no-distractors", action="store_true", help="no distractor objects")
    parser.add_argument("--person", type=float, default=0.25, help="probability of a person's arm in an image (default 0.25)")
    parser.add_argument("--shard-size", type=positive_int, default=256, help="images per shard (default 256)")
    parser.add_argument("--workers", type=positive_int, default=None, help="worker processes (default: one per core)")
    parser.add_argument("--ray", action="store_true", help="render the shards as Ray tasks")
    parser.add_argument("--ray-address", default="auto", help="Ray cluster address (default auto; a local instance when none is running)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


class _Progress:
    """tqdm's bar when installed, else a counter on stderr."""

    def __init__(self, total: int, done: int, quiet: bool) -> None:
        self.total, self.done, self.quiet = total, done, quiet
        self.bar = None
        if quiet:
            return
        try:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, unit="img", desc="rendering", file=sys.stderr)
        except ImportError:
            self._print()

    def _print(self) -> None:
        print(f"\rrendering: {self.done}/{self.total} images", end="", file=sys.stderr, flush=True)

    def update(self, n: int) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
        elif not self.quiet:
            self._print()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        elif not self.quiet:
            print(file=sys.stderr)


def _generator(module: str):
    """The `generate_shard` of a generator module (earcore.sim.robot_images, ...)."""
    import importlib

    return importlib.import_module(module).generate_shard


def _local(module: str, options, todo: list[int], folder: Path, workers: int) -> Iterator[int]:
    if workers == 1:
        generate_shard = _generator(module)
        for index in todo:
            yield generate_shard(options, index, folder)
        return
    context = multiprocessing.get_context("spawn")  # each worker opens its own pybullet world
    with context.Pool(workers) as pool:
        yield from pool.imap_unordered(_shard_task, [(module, options, i, folder) for i in todo], chunksize=1)


def _shard_task(args) -> int:
    module, *rest = args
    return _generator(module)(*rest)


def _ray(module: str, options, todo: list[int], folder: Path, address: str) -> Iterator[int]:
    try:
        import ray
    except ImportError:
        raise ImportError("--ray needs Ray: pip install 'ray[default]'") from None
    generate_shard = _generator(module)

    if not ray.is_initialized():
        try:
            ray.init(address=address, log_to_driver=False)
        except ConnectionError:
            if address != "auto":
                raise
            print(f"{PROG}: no Ray cluster running here; starting a local Ray instance", file=sys.stderr)
            ray.init(log_to_driver=False)
    task = ray.remote(generate_shard)
    pending = [task.remote(options, i, str(folder.resolve())) for i in todo]
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield ray.get(done[0])


def _robot_options(args):
    from earcore.sim.robot_images import RobotImageOptions

    width, height = args.size
    options = RobotImageOptions(
        robots=tuple(r.strip().lower() for r in args.robots.split(",") if r.strip()),
        mode=args.mode,
        width=width,
        height=height,
        seed=args.seed,
        scale=1.0 if args.scale is None else args.scale,
        count=args.count,
        meshes=args.meshes,
        distractors=not args.no_distractors,
        person=args.person,
        shard_size=args.shard_size,
    ).validate()
    if options.mode == "random" and args.count is None and args.scale is None:
        print(f"{PROG}: random mode without --count: the papers' totals per robot", file=sys.stderr)
    return options


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "parts":
        from earcore.app.parts import generate_main

        return generate_main(argv[1:], prog="earcore dataset parts")
    from earcore.validate import ConfigError

    args = _parser().parse_args(argv)
    try:
        options = _robot_options(args)
    except ConfigError as exc:
        return fail(PROG, str(exc))
    return render(PROG, "earcore.sim.robot_images", options, args.out, args.workers, args.ray, args.ray_address, args.quiet)


def render(prog: str, module: str, options, folder: Path, workers: int | None, use_ray: bool, ray_address: str, quiet: bool) -> int:
    """Render (or complete) the dataset `options` describe into `folder` with the
    generator `module` (its plan_shards, manifest_for and generate_shard)."""
    import importlib

    from earcore.learning.errors import DatasetError
    from earcore.learning.shards import complete_shards, read_manifest, write_manifest

    generator = importlib.import_module(module)
    shards = generator.plan_shards(options)
    manifest = generator.manifest_for(options, shards)
    if (folder / "manifest.json").exists():
        try:
            existing = read_manifest(folder)
        except DatasetError as exc:
            return fail(prog, f"{exc}; choose another --out")
        if existing != manifest:
            theirs, ours = existing.get("generator", {}), manifest["generator"]
            changed = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k)) or ["format"]
            return fail(
                prog,
                f"{folder} holds a dataset made with other options ({', '.join(changed)} differ); rerun with its options to complete it, or choose another --out",
            )
    elif folder.exists() and any(folder.iterdir()):
        return fail(prog, f"{folder} exists and is not a dataset folder; choose an empty or new --out")
    folder.mkdir(parents=True, exist_ok=True)
    write_manifest(folder, manifest)
    complete = complete_shards(folder, manifest)
    todo = [i for i, entry in enumerate(manifest["shards"]) if entry["name"] not in complete]
    total = sum(len(s) for s in shards)
    done = total - sum(len(shards[i]) for i in todo)
    workers = min(workers or multiprocessing.cpu_count(), max(1, len(todo)))
    started = time.perf_counter()
    progress = _Progress(total, done, quiet)
    rendered = 0
    try:
        source = _ray(module, options, todo, folder, ray_address) if use_ray else _local(module, options, todo, folder, workers)
        for n in source:
            rendered += n
            progress.update(n)
    finally:
        progress.close()
    seconds = time.perf_counter() - started
    rate = rendered / seconds if seconds > 0 else 0.0
    print(f"{rendered} images in {seconds:.1f} s ({rate:.1f} images/s; {done} already there), {total} in {folder}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
