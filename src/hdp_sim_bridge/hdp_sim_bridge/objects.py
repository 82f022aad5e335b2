"""Task objects built from box and cylinder primitives, as URDF text.

pybullet's createMultiBody cannot give joints limits, so articulated objects
(drawers, lids, seats, doors, handles) are written as URDF and loaded from a
per-process cache directory. Every object's frame sits on the table top with
+x pointing towards the robot, so a task only picks a position and a yaw.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
import tempfile
from pathlib import Path

from hdp_msgs_py.instructions import DRAWER_NAMES

# RGB of the named colours task variations use (RLBench uses 20; hdp_msgs_py.instructions.COLOUR_NAMES).
COLOURS = {
    'red': (1.0, 0.0, 0.0), 'maroon': (0.5, 0.0, 0.0), 'lime': (0.0, 1.0, 0.0),
    'green': (0.0, 0.5, 0.0), 'blue': (0.0, 0.0, 1.0), 'navy': (0.0, 0.0, 0.5),
    'yellow': (1.0, 1.0, 0.0), 'cyan': (0.0, 1.0, 1.0), 'magenta': (1.0, 0.0, 1.0),
    'silver': (0.75, 0.75, 0.75), 'gray': (0.5, 0.5, 0.5), 'orange': (1.0, 0.5, 0.0),
    'olive': (0.5, 0.5, 0.0), 'purple': (0.5, 0.0, 0.5), 'teal': (0.0, 0.5, 0.5),
    'azure': (0.0, 0.5, 1.0), 'violet': (0.5, 0.0, 1.0), 'rose': (1.0, 0.0, 0.5),
    'black': (0.0, 0.0, 0.0), 'white': (1.0, 1.0, 1.0),
}

_WOOD = (0.55, 0.4, 0.25, 1)
_PALE = (0.85, 0.85, 0.8, 1)
_METAL = (0.6, 0.6, 0.65, 1)


@dataclasses.dataclass(frozen=True)
class Part:
    """One collision+visual primitive of a link, at ``xyz`` in the link frame."""
    size: tuple            # box (x, y, z) or cylinder (radius, length)
    xyz: tuple = (0, 0, 0)
    rgba: tuple = _WOOD
    cylinder: bool = False
    rpy: tuple = (0, 0, 0)

    def xml(self) -> str:
        geometry = (f'<cylinder radius="{self.size[0]}" length="{self.size[1]}"/>' if self.cylinder
                    else f'<box size="{_v(self.size)}"/>')
        origin = f'<origin xyz="{_v(self.xyz)}" rpy="{_v(self.rpy)}"/>'
        return (f'<visual>{origin}<geometry>{geometry}</geometry>'
                f'<material name="c{_v(self.rgba).replace(" ", "_")}"><color rgba="{_v(self.rgba)}"/></material>'
                f'</visual><collision>{origin}<geometry>{geometry}</geometry></collision>')


def _v(values) -> str:
    return ' '.join(f'{float(x):.6g}' for x in values)


def _link(name: str, parts: list[Part], mass: float) -> str:
    inertia = max(mass, 1e-3) * 1e-3   # small, isotropic: these objects never tumble
    return (f'\n<link name="{name}"><inertial><mass value="{mass}"/>'
            f'<inertia ixx="{inertia}" iyy="{inertia}" izz="{inertia}" ixy="0" ixz="0" iyz="0"/>'
            f'</inertial>{"".join(p.xml() for p in parts)}</link>')


def _joint(name: str, kind: str, parent: str, child: str, xyz, axis=(0, 0, 1),
           limits=(0.0, 0.0)) -> str:
    limit = (f'<limit lower="{limits[0]}" upper="{limits[1]}" effort="100" velocity="2"/>'
             if kind in ('revolute', 'prismatic') else '')
    return (f'\n<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{_v(xyz)}" rpy="0 0 0"/><axis xyz="{_v(axis)}"/>{limit}'
            f'<dynamics damping="0.5" friction="0.05"/></joint>')


def _robot(name: str, body: str) -> str:
    # one element a line: pybullet's XML reader fails on very long lines
    return f'<?xml version="1.0"?>\n<robot name="{name}">\n{body}\n</robot>\n'


@functools.cache
def _cache_dir() -> Path:
    path = Path(tempfile.gettempdir()) / f'hdp_objects_{os.getuid()}_{os.getpid()}'
    path.mkdir(parents=True, exist_ok=True)
    return path


def urdf_file(text: str) -> str:
    """Write URDF text once per process and return the file path pybullet loads."""
    path = _cache_dir() / f'{hashlib.sha1(text.encode()).hexdigest()[:16]}.urdf'
    if not path.exists():
        path.write_text(text)
    return str(path)


# -- articulated objects ---------------------------------------------------------------


def cabinet(width=0.34, depth=0.30, drawer_height=0.08, legs=0.08) -> str:
    """A chest of three drawers on legs; joints `drawer_<bottom|middle|top>` slide out along +x.

    The legs lift the bottom handle clear of the table for the Panda's 20 cm wide hand.
    """
    height = 3 * drawer_height + 0.04
    t = 0.012                                     # wall thickness
    carcass = [Part((0.03, 0.03, legs), (x, y, legs / 2))
               for x in (depth / 2 - 0.02, -depth / 2 + 0.02) for y in (width / 2 - 0.02, -width / 2 + 0.02)]
    carcass += [Part((depth, width, t), (0, 0, t / 2)),                      # bottom
               Part((depth, width, t), (0, 0, height - t / 2)),              # top
               Part((depth, t, height), (0, width / 2 - t / 2, height / 2)),  # sides
               Part((depth, t, height), (0, -width / 2 + t / 2, height / 2)),
               Part((t, width, height), (-depth / 2 + t / 2, 0, height / 2))]  # back
    for k in range(1, 3):                         # shelves between drawers
        carcass.append(Part((depth, width, t / 2), (0, 0, 0.02 + k * drawer_height)))
    carcass = carcass[:4] + [dataclasses.replace(p, xyz=(p.xyz[0], p.xyz[1], p.xyz[2] + legs))
                             for p in carcass[4:]]
    links, joints = [_link('base', carcass, 0.0)], []
    for k, name in enumerate(DRAWER_NAMES):
        z = 0.02 + (k + 0.5) * drawer_height
        inner_w, inner_h, d = width - 2.5 * t, drawer_height - 0.02, depth - 0.03
        parts = [Part((t, inner_w, inner_h), (d / 2, 0, 0), _PALE),          # front panel
                 Part((d, inner_w, t), (0, 0, -inner_h / 2 + t / 2), _PALE),
                 Part((d, t, inner_h * 0.6), (0, inner_w / 2 - t / 2, -inner_h * 0.2), _PALE),
                 Part((d, t, inner_h * 0.6), (0, -inner_w / 2 + t / 2, -inner_h * 0.2), _PALE),
                 Part((t, inner_w, inner_h * 0.6), (-d / 2, 0, -inner_h * 0.2), _PALE),
                 # handle: a bar 4 cm proud of the front, on two posts
                 Part((0.012, 0.10, 0.012), (d / 2 + 0.04, 0, 0), _METAL),
                 Part((0.035, 0.01, 0.01), (d / 2 + 0.0225, 0.045, 0), _METAL),
                 Part((0.035, 0.01, 0.01), (d / 2 + 0.0225, -0.045, 0), _METAL)]
        links.append(_link(f'drawer_{name}_link', parts, 0.3))
        joints.append(_joint(f'drawer_{name}', 'prismatic', 'base', f'drawer_{name}_link',
                             (0.01, 0, legs + z), axis=(1, 0, 0), limits=(0.0, 0.26)))
    return _robot('cabinet', ''.join(links + joints))


def drawer_handle_offset(depth=0.30) -> float:
    """x of the drawer handle bar in the drawer link frame."""
    return (depth - 0.03) / 2 + 0.04


def hinged_box(size=(0.16, 0.24, 0.15)) -> str:
    """A box with a lid hinged along its back (-x) edge; joint `lid` opens upwards (+)."""
    sx, sy, sz = size
    t = 0.01
    walls = [Part((sx, sy, t), (0, 0, t / 2)),
             Part((t, sy, sz), (sx / 2 - t / 2, 0, sz / 2)), Part((t, sy, sz), (-sx / 2 + t / 2, 0, sz / 2)),
             Part((sx, t, sz), (0, sy / 2 - t / 2, sz / 2)), Part((sx, t, sz), (0, -sy / 2 + t / 2, sz / 2))]
    lid = [Part((sx, sy, t), (sx / 2, 0, t / 2), _PALE),
           Part((0.03, 0.08, 0.012), (sx + 0.012, 0, t / 2), _METAL)]     # lip to lift it by
    return _robot('box', _link('base', walls, 0.0) + _link('lid_link', lid, 0.2)
                  + _joint('lid', 'revolute', 'base', 'lid_link', (-sx / 2, 0, sz), axis=(0, -1, 0),
                           limits=(0.0, 2.6)))


def toilet() -> str:
    """A bowl on a pedestal with a cistern; joint `seat` (hinge at the back) lifts the seat."""
    bowl_top = 0.16
    base = [Part((0.14, 0.16, bowl_top - 0.02), (0.0, 0, (bowl_top - 0.02) / 2), _PALE),
            Part((0.08, 0.28, 0.30), (-0.14, 0, 0.15), _PALE)]                  # cistern
    seat = [Part((0.24, 0.22, 0.015), (0.12, 0, 0.0075), (0.95, 0.95, 0.95, 1)),
            Part((0.03, 0.07, 0.012), (0.255, 0, 0.006), _METAL)]               # grip tab
    return _robot('toilet', _link('base', base, 0.0) + _link('seat_link', seat, 0.2)
                  + _joint('seat', 'revolute', 'base', 'seat_link', (-0.095, 0, bowl_top),
                           axis=(0, -1, 0), limits=(0.0, 1.75)))


def door(width=0.30, height=0.40) -> str:
    """A door in a frame: joint `door` (hinge at the +y edge, opens towards +x) and
    joint `handle` (a lever on the +x side reaching towards the hinge, turns down)."""
    t = 0.02
    frame = [Part((0.04, t, height + t), (0, width / 2 + t / 2 + 0.004, (height + t) / 2)),
             Part((0.04, t, height + t), (0, -width / 2 - t / 2 - 0.004, (height + t) / 2)),
             Part((0.04, width + 2 * t + 0.008, t), (0, 0, height + t + t / 2))]
    leaf = [Part((t, width, height), (0, -width / 2, height / 2 + 0.01), _PALE)]
    # the bar stands 7 cm proud of the leaf, room for a finger behind it
    lever = [Part((0.07, 0.012, 0.012), (0.035, 0, 0), _METAL),
             Part((0.012, 0.10, 0.012), (0.07, 0.05, 0), _METAL)]
    return _robot('door', _link('base', frame, 0.0) + _link('door_link', leaf, 0.5)
                  + _link('handle_link', lever, 0.05)
                  + _joint('door', 'revolute', 'base', 'door_link', (0, width / 2, 0), axis=(0, 0, 1),
                           limits=(0.0, 1.6))
                  + _joint('handle', 'revolute', 'door_link', 'handle_link',
                           (t / 2, -width + 0.05, height * 0.5), axis=(-1, 0, 0), limits=(0.0, 1.0)))
