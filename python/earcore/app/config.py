"""`earcore run`'s configuration: the cell, the perception loop and the planner in one
typed structure, loaded from and dumped to TOML. Field names are the TOML keys; each
area owns its section (`earcore.sim.config`, `earcore.perception.config`,
`earcore.planning.config`, `earcore.pose.config`)."""

from __future__ import annotations

import tomllib
import typing
from dataclasses import MISSING, asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from earcore.perception.config import PerceptionConfig
from earcore.planning.config import PlanningConfig
from earcore.pose.config import PoseConfig
from earcore.sim.config import CellConfig
from earcore.validate import ConfigError, non_negative, positive, vector

__all__ = ["RunConfig", "dump_toml", "load_config"]


@dataclass
class RunConfig:
    #: Simulated seconds: long enough for the danger the arm leaves (~3 s) to fade (~21 s).
    duration: float = 30.0
    #: Snapshot times (s) of the danger map (PNG).
    snapshots: list[float] = field(default_factory=lambda: [2.5, 10.0, 20.0, 29.9])
    #: Joint targets the robot shuttles between (A-B-A); empty = the robot's defaults.
    waypoints: list[list[float]] = field(default_factory=list)
    cell: CellConfig = field(default_factory=CellConfig)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    planning: PlanningConfig = field(default_factory=PlanningConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)

    def validate(self) -> RunConfig:
        """Raise `ConfigError` naming the first setting out of its range; returns self.
        (Waypoints are checked against the robot's joints and limits when it is built.)"""
        positive(self.duration, "duration")
        for i, t in enumerate(self.snapshots):
            non_negative(t, f"snapshots[{i}]")
        for i, w in enumerate(self.waypoints):
            vector(w, f"waypoints[{i}]")
        self.cell.validate("cell")
        self.perception.validate("perception")
        self.planning.validate("planning")
        self.pose.validate("pose", [c.name for c in self.cell.cameras])
        if self.pose.camera and self.cell.renderer != "pybullet":
            raise ConfigError(
                f"pose.camera needs cell.renderer = \"pybullet\" (the pose networks learned the tiny renderer's "
                f"textured, shaded look; the rasterizer draws none of it), got {self.cell.renderer!r}"
            )
        return self


#: Keys of `[planning]` that were renamed to the keyword arguments they feed.
RENAMED = {
    "motion_resolution": "resolution",
    "risk_beta": "beta",
    "risk_threshold": "threshold",
    "straight_acceleration_share": "straight_share",
}


def _dataclass_in(hint) -> Any:
    """The dataclass a field holds (`X`) or lists (`list[X]`), if any."""
    if is_dataclass(hint):
        return hint
    if typing.get_origin(hint) is list:
        (item,) = typing.get_args(hint)
        return item if is_dataclass(item) else None
    return None


def _list(value, where: str) -> list:
    if not isinstance(value, list):
        raise ConfigError(f"{where} must be an array, got {value!r}")
    return value


def _build(cls, data: dict[str, Any], where: str):
    """`cls(**data)`, building nested dataclasses (and lists of them) by their field
    types and turning TOML arrays into the tuples the fields declare."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a table ([{where}]), got {data!r}")
    known = {f.name: f for f in fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        renamed = [f"{k} is now {RENAMED[k]}" for k in sorted(unknown) if k in RENAMED]
        hint = f" ({'; '.join(renamed)})" if renamed else ""
        raise ConfigError(f"{where or 'the top level'}: unknown keys {sorted(unknown)}{hint}; known: {sorted(known)}")
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        hint = hints[name]
        key = f"{where}.{name}" if where else name
        nested = _dataclass_in(hint)
        if nested is not None and typing.get_origin(hint) is list:
            value = [_build(nested, v, f"{key}[{i}]") for i, v in enumerate(_list(value, key))]
        elif nested is not None:
            value = _build(nested, value, key)
        elif typing.get_origin(hint) is tuple:
            value = tuple(_list(value, key))
        elif typing.get_origin(hint) is list and typing.get_origin(typing.get_args(hint)[0]) is tuple:
            value = [tuple(_list(v, f"{key}[{i}]")) for i, v in enumerate(_list(value, key))]
        elif typing.get_origin(hint) is list:
            value = _list(value, key)
        elif hint is bool and not isinstance(value, bool):
            raise ConfigError(f"{key} must be true or false, got {value!r}")
        elif hint is str and not isinstance(value, str):
            raise ConfigError(f"{key} must be a string, got {value!r}")
        kwargs[name] = value
    missing = [f.name for f in fields(cls) if f.name not in kwargs and f.default is MISSING and f.default_factory is MISSING]
    if missing:
        raise ConfigError(f"{where or 'the top level'}: missing {', '.join(missing)}")
    return cls(**kwargs)


def load_config(path: str | Path) -> RunConfig:
    """Read a TOML file (missing keys keep their defaults; unknown keys are errors)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read {path}: {exc}") from exc
    try:
        return _build(RunConfig, data, "").validate()
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(config: RunConfig) -> str:
    """The configuration as TOML (round-trips through `load_config`)."""
    lines: list[str] = []

    def table(obj, prefix: str) -> None:
        data = asdict(obj)
        nested: list[tuple[str, Any]] = []
        for f in fields(obj):
            value = getattr(obj, f.name)
            if is_dataclass(value):
                nested.append((f.name, value))
            elif isinstance(value, list) and value and is_dataclass(value[0]):
                nested.append((f.name, value))
            else:
                lines.append(f"{f.name} = {_toml_value(data[f.name])}")
        for name, value in nested:
            if isinstance(value, list):
                for cam in value:
                    lines.append(f"\n[[{prefix}{name}]]")
                    for cf in fields(cam):
                        lines.append(f"{cf.name} = {_toml_value(getattr(cam, cf.name))}")
            else:
                lines.append(f"\n[{prefix}{name}]")
                table(value, f"{prefix}{name}.")

    table(config, "")
    return "\n".join(lines) + "\n"
