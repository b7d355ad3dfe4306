"""The `earcore` command: one line on stderr and a non-zero exit for anything the user
can fix (a bad option, a bad configuration file, a missing file); `--debug` shows the
traceback instead."""

from __future__ import annotations

import sys

from earcore.app.arguments import Parser

__all__ = ["main"]


def _is_user_error(exc: BaseException) -> bool:
    """Failures a user can act on (a bad value, a missing file, a domain failure such as
    a camera that never saw the board): reported in one line, not as a traceback."""
    from earcore.errors import EarcoreError

    return isinstance(exc, (ValueError, TypeError, OSError, OverflowError, EarcoreError))


def _version() -> int:
    try:
        import earcore

        version = earcore.__version__
    except ImportError as exc:
        print(f"earcore: the compiled extension failed to load:\n  {exc}", file=sys.stderr)
        return 1
    print(f"earcore {version} (extension {earcore._earcore.__file__})")
    return 0


def _command(name: str, rest: list[str]) -> int:
    if name == "run":
        from earcore.app.run import main as run_main

        return run_main(rest)
    if name == "config":
        from earcore.app.run import config_main

        return config_main(rest)
    if name == "calibrate":
        from earcore.app.calibrate import main as calibrate_main

        return calibrate_main(rest)
    if name == "experiment":
        from earcore.app.experiments.planning import main as experiment_main

        return experiment_main(rest)
    if name == "dataset":
        from earcore.app.dataset import main as dataset_main

        return dataset_main(rest)
    if name == "parts":
        from earcore.app.parts import main as parts_main

        return parts_main(rest)
    if name == "charge":
        from earcore.app.charge import main as charge_main

        return charge_main(rest)
    if name in ("train", "evaluate", "export"):
        from earcore.app.pose import evaluate_main, export_main, train_main

        return {"train": train_main, "evaluate": evaluate_main, "export": export_main}[name](rest)
    from earcore.app.demo import main as demo_main

    return demo_main(rest)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = Parser(prog="earcore", description="Environment-aware robot arm toolkit.")
    parser.add_argument("--version", action="store_true", help="print the version (proves the extension loads)")
    parser.add_argument("--debug", action="store_true", help="show the full traceback of an error")
    sub = parser.add_subparsers(dest="command")
    sub.add_parser("demo", help="map demo: cameras, an obstacle passing, danger decaying (PNG + summary)", add_help=False)
    sub.add_parser("run", help="the simulated cell end to end: robot, cameras, a person, the map (PNGs + JSON)", add_help=False)
    sub.add_parser("config", help="`earcore config dump`: every option of `earcore run` as TOML", add_help=False)
    sub.add_parser("calibrate", help="Paper I's automatic camera calibration in the simulated cell (YAML file)", add_help=False)
    sub.add_parser("experiment", help="the papers' experiments, e.g. `earcore experiment table2` (Paper II)", add_help=False)
    sub.add_parser("dataset", help="labelled images from the simulator, e.g. `earcore dataset robots --out data`", add_help=False)
    sub.add_parser("parts", help="parts on the table: `earcore parts generate|train|evaluate` (IROS 2018 detector)", add_help=False)
    sub.add_parser("charge", help="the EV charging station (Paper III): find the port, plug in and out (`earcore charge --runs 20`)", add_help=False)
    sub.add_parser("train", help="train a network, e.g. `earcore train pose --data data --out run`", add_help=False)
    sub.add_parser("evaluate", help="evaluate a trained network on held-out images (`earcore evaluate pose`)", add_help=False)
    sub.add_parser("export", help="export a trained network to ONNX (`earcore export pose`)", add_help=False)
    args, rest = parser.parse_known_args(argv)
    if args.version:
        return _version()
    if args.command is None:
        if rest:
            parser.error(f"unrecognized arguments: {' '.join(rest)}")
        parser.print_help()
        return 0
    if "--debug" in rest:  # also accepted after the command
        rest = [a for a in rest if a != "--debug"]
        args.debug = True
    try:
        return _command(args.command, rest)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"earcore {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if args.debug or not _is_user_error(exc):
            raise
        from earcore.errors import ConfigError

        message = " ".join(str(exc).split()) or type(exc).__name__
        hint = "" if isinstance(exc, ConfigError) else " (--debug shows where)"
        print(f"earcore {args.command}: error: {message}{hint}", file=sys.stderr)
        return 2 if isinstance(exc, (ValueError, TypeError)) else 1


if __name__ == "__main__":
    sys.exit(main())
