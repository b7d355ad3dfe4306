"""The package's layers import only downward: the foundation (top-level modules) knows
no area, the areas (perception, planning, then calibration) never import the simulator
or the applications, the simulator never imports the applications. Checked on the
installed package's source, function-level imports included."""

from __future__ import annotations

import ast
from pathlib import Path

import earcore

#: Rank of each area; a module may import its own area and lower ranks only. Areas of
#: the same rank may not import each other.
RANKS = {"": 0, "perception": 1, "planning": 1, "learning": 1, "calibration": 2, "pose": 2, "parts": 2, "charging": 2, "sim": 3, "app": 4}
PACKAGE = Path(earcore.__file__).resolve().parent


def area_of(module: str) -> str:
    """`earcore.planning.rrt` -> "planning"; top-level modules -> "" (the foundation)."""
    parts = module.split(".")
    if len(parts) < 2 or parts[1] not in RANKS:
        return "app" if parts[1:2] == ["__main__"] else ""
    return parts[1]


def imported_modules(source: str, module: str, *, package: bool = False) -> list[tuple[int, str]]:
    """(line, module) of every earcore import in `source` (of `module`; `package`: the
    source is the package's `__init__.py`), relative imports resolved, `from earcore
    import sub` read as `earcore.sub`, and `importlib.import_module("earcore...")` /
    `__import__("earcore...")` with a literal name counted too."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            target = node.args[0].value
            if name in ("import_module", "__import__") and isinstance(target, str) and target.split(".")[0] == "earcore":
                found.append((node.lineno, target))
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "earcore"]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                # A package's `from . import x` is relative to the package itself.
                parts = module.split(".")
                parent = parts[: len(parts) - node.level + (1 if package else 0)]
                base = ".".join(parent + ([base] if base else []))
            if base.split(".")[0] != "earcore":
                continue
            found.append((node.lineno, base))
            if base == "earcore":
                found += [(node.lineno, f"earcore.{a.name}") for a in node.names if a.name in RANKS]
    return found


def violations(source: str, module: str, *, package: bool = False) -> list[str]:
    own = area_of(module)
    bad = []
    for line, target in imported_modules(source, module, package=package):
        theirs = area_of(target)
        if theirs == own:
            continue
        if RANKS[theirs] > RANKS[own] or (RANKS[theirs] == RANKS[own] and theirs != own):
            bad.append(f"{module}:{line} imports {target} ({own or 'foundation'} -> {theirs or 'foundation'})")
    return bad


def package_modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).with_suffix("")
        parts = ["earcore", *rel.parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.append((".".join(parts), path))
    return out


def test_every_area_is_found():
    areas = {area_of(m) for m, _ in package_modules()}
    assert areas == set(RANKS), areas


def test_no_module_imports_upward():
    bad = [
        v for module, path in package_modules() for v in violations(path.read_text(), module, package=path.name == "__init__.py")
    ]
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_the_check_catches_upward_and_sideways_imports():
    assert violations("from earcore.sim.cell import SimulatedCell", "earcore.planning.executive")
    assert violations("def f():\n    import earcore.app.run\n", "earcore.calibration.procedure")
    assert violations("from ..app import run", "earcore.sim.cell")
    assert violations("from earcore import planning", "earcore.cloud")
    assert violations("from earcore.perception import PerceptionPipeline", "earcore.planning.reflex")
    assert not violations("from earcore.planning.ik import solve_ik", "earcore.calibration.procedure")
    assert not violations("import earcore\nfrom earcore.transforms import look_at", "earcore.sim.cell")
    assert violations("from ..sim import cell", "earcore.planning", package=True)
    assert violations("from . import app", "earcore", package=True)
    assert not violations("from . import transforms", "earcore", package=True)
    assert violations("import importlib\nimportlib.import_module('earcore.app.run')", "earcore.perception.pipeline")
    assert violations("__import__('earcore.sim')", "earcore.planning.rrt")
