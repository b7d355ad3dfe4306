"""The `earcore` command."""

from __future__ import annotations

import argparse
import sys


def _version() -> int:
    try:
        import earcore
    except ImportError as exc:
        print(f"earcore: the compiled extension failed to load:\n  {exc}", file=sys.stderr)
        return 1
    print(f"earcore {earcore.__version__} (extension {earcore._earcore.__file__})")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="earcore", description="Environment-aware robot arm toolkit.")
    parser.add_argument("--version", action="store_true", help="print the version (proves the extension loads)")
    sub = parser.add_subparsers(dest="command")
    sub.add_parser("demo", help="map demo: cameras, an obstacle passing, danger decaying (PNG + summary)", add_help=False)
    sub.add_parser("run", help="the simulated cell end to end: robot, cameras, a person, the map (PNGs + JSON)", add_help=False)
    sub.add_parser("config", help="`earcore config dump`: every option of `earcore run` as TOML", add_help=False)
    sub.add_parser("calibrate", help="Paper I's automatic camera calibration in the simulated cell (YAML file)", add_help=False)
    sub.add_parser("experiment", help="the papers' experiments, e.g. `earcore experiment table2` (Paper II)", add_help=False)
    args, rest = parser.parse_known_args(argv)
    if args.version:
        return _version()
    if args.command == "run":
        from earcore.app.run import main as run_main

        return run_main(rest)
    if args.command == "config":
        from earcore.app.run import config_main

        return config_main(rest)
    if args.command == "calibrate":
        from earcore.app.calibrate import main as calibrate_main

        return calibrate_main(rest)
    if args.command == "experiment":
        from earcore.app.experiments.planning import main as experiment_main

        return experiment_main(rest)
    if args.command == "demo":
        from earcore.app.demo import main as demo_main

        return demo_main(rest)
    parser.print_help()
    return 0 if not argv else 2


if __name__ == "__main__":
    sys.exit(main())
