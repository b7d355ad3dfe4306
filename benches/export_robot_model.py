"""Write a built-in robot's chain and fitted bodies as plain text for the criterion
benches (`benches/data/<name>.model`), so `cargo bench` needs no Python or URDF.

    python benches/export_robot_model.py ur5

Format, one item per line: `joint name kind parent child x y z roll pitch yaw ax ay az
lower upper` and `body link shape ax ay az bx by bz radius` (links are indices into the
`links` line).
"""

from __future__ import annotations

import sys
from pathlib import Path

import earcore.robots
from earcore.urdf import parse_urdf


def export(name: str) -> Path:
    model = earcore.robots.load(name)
    urdf = parse_urdf(earcore.robots.urdf_path(name))
    index = {link: i for i, link in enumerate(urdf.links)}
    lines = [f"# {name}: exported by benches/export_robot_model.py (padding {model.padding} m)"]
    lines.append("links " + " ".join(urdf.links))
    for j in urdf.joints:
        numbers = [*j.xyz, *j.rpy, *j.axis, j.lower, j.upper]
        lines.append(f"joint {j.name} {j.kind} {index[j.parent]} {index[j.child]} " + " ".join(repr(float(v)) for v in numbers))
    for link, body in enumerate(model.link_bodies):
        if body is not None:
            a, b, radius, shape = body
            lines.append(f"body {link} {shape} " + " ".join(repr(float(v)) for v in (*a, *b, radius)))
    out = Path(__file__).parent / "data" / f"{name}.model"
    out.write_text("\n".join(lines) + "\n")
    return out


if __name__ == "__main__":
    for robot in sys.argv[1:] or ["ur5"]:
        print(export(robot))
