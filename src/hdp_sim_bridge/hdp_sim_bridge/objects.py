"""Task objects built from box and cylinder primitives, as URDF text.

pybullet's createMultiBody cannot give joints limits, so articulated objects
(drawers, lids, seats, doors, handles) are written as URDF and loaded from a
per-process cache directory. Every object's frame sits on the table top with
+x pointing towards the robot, so a task only picks a position and a yaw.
"""

from __future__ import annotations

import atexit
import dataclasses
import functools
import hashlib
import shutil
import tempfile
from pathlib import Path

from hdp_data.instructions import DRAWER_NAMES

# RGB of the named colours task variations use (RLBench uses 20; hdp_data.instructions.COLOUR_NAMES).
COLOURS = {
    'red': (1.0, 0.0, 0.0), 'maroon': (0.5, 0.0, 0.0), 'lime': (0.0, 1.0, 0.0),
    'green': (0.0, 0.5, 0.0), 'blue': (0.0, 0.0, 1.0), 'navy': (0.0, 0.0, 0.5),
    'yellow': (1.0, 1.0, 0.0), 'cyan': (0.0, 1.0, 1.0), 'magenta': (1.0, 0.0, 1.0),
    'silver': (0.75, 0.75, 0.75), 'gray': (0.5, 0.5, 0.5), 'orange': (1.0, 0.5, 0.0),
    'olive': (0.5, 0.5, 0.0), 'purple': (0.5, 0.0, 0.5), 'teal': (0.0, 0.5, 0.5),
    'azure': (0.0, 0.5, 1.0), 'violet': (0.5, 0.0, 1.0), 'rose': (1.0, 0.0, 0.5),
    'black': (0.0, 0.0, 0.0), 'white': (1.0, 1.0, 1.0),
}

# Sizes the tasks place their grasps by (m).
PAN_HEIGHT = 0.07
LID_KNOB = (0.012, 0.035)              # radius, height
GRILL_DEPTH = 0.26                     # front to back: the lid's hinge to its front edge
GRILL_HANDLE = (0.008, 0.05)           # bar radius, how far it stands in front of the lid
MICROWAVE_DOOR_WIDTH = 0.32
MICROWAVE_HANDLE = (0.008, 0.045)      # bar radius, how far it stands proud of the door
OVEN_HANDLE = (0.008, 0.045)           # bar radius, how far it stands proud of the door
OVEN_DOOR_HEIGHT = 0.20
KNIFE_BLOCK_HEIGHT = 0.05
KNIFE_HANDLE = (0.024, 0.10, 0.022)    # x, y, z
CHOPPING_BOARD = (0.20, 0.30, 0.015)   # x, y, z

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
    """This process's folder of generated URDFs (pybullet loads files, not strings), removed at exit:
    every simulator process (collection workers, evaluation ranks, the bridge) makes one."""
    path = Path(tempfile.mkdtemp(prefix='hdp_objects_'))
    atexit.register(shutil.rmtree, path, ignore_errors=True)
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


def saucepan() -> str:
    """A pan (solid body and a long side handle along -y); its top is at PAN_HEIGHT."""
    pan = [Part((0.09, PAN_HEIGHT), (0, 0, PAN_HEIGHT / 2), _METAL, cylinder=True),
           Part((0.14, 0.025, 0.015), (0, -0.16, PAN_HEIGHT - 0.01), (0.15, 0.15, 0.15, 1), rpy=(0, 0, 1.5708))]
    return _robot('saucepan', _link('base', pan, 0.0))


def saucepan_lid() -> str:
    """A free lid: a disc with a knob on top, frame at the disc's underside centre.
    The knob (2.4 cm across, 3.5 cm tall) is what the gripper takes."""
    lid = [Part((0.095, 0.012), (0, 0, 0.006), (0.3, 0.3, 0.35, 1), cylinder=True),
           Part((LID_KNOB[0], LID_KNOB[1]), (0, 0, 0.012 + LID_KNOB[1] / 2), (0.1, 0.1, 0.1, 1), cylinder=True)]
    return _robot('saucepan_lid', _link('base', lid, 0.15))


def grill(depth=GRILL_DEPTH, width=0.34, height=0.12) -> str:
    """A barbecue: a body with a lid hinged along its back top edge; joint `lid` opens
    upwards (+) and the handle is a bar along y in front of the lid's front edge."""
    body = [Part((depth, width, height - 0.03), (0, 0, 0.03 + (height - 0.03) / 2), (0.15, 0.15, 0.15, 1))]
    body += [Part((0.03, 0.03, 0.03), (x, y, 0.015), _METAL)
             for x in (depth / 2 - 0.03, -depth / 2 + 0.03) for y in (width / 2 - 0.03, -width / 2 + 0.03)]
    dark = (0.25, 0.05, 0.05, 1)
    lid = [Part((depth, width, 0.015), (depth / 2, 0, 0.0075), dark),
           Part((depth * 0.8, width * 0.9, 0.04), (depth / 2, 0, 0.035), dark),     # the dome
           Part((0.012, width, 0.03), (depth + 0.006, 0, -0.005), dark),             # front skirt
           Part((GRILL_HANDLE[0], 0.16), (depth + GRILL_HANDLE[1], 0, 0.02), _METAL, cylinder=True,
                rpy=(1.5708, 0, 0))]
    lid += [Part((GRILL_HANDLE[1], 0.012, 0.012), (depth + GRILL_HANDLE[1] / 2, y, 0.02), _METAL)
            for y in (0.07, -0.07)]
    return _robot('grill', _link('base', body, 0.0) + _link('lid_link', lid, 0.4)
                  + _joint('lid', 'revolute', 'base', 'lid_link', (-depth / 2, 0, height), axis=(0, -1, 0),
                           limits=(0.0, 1.9)))


def microwave(depth=0.30, width=0.44, height=0.26, door_width=MICROWAVE_DOOR_WIDTH) -> str:
    """A microwave: joint `door` hinged on a vertical axis at the -y edge of the front,
    opening towards +x (+), and a vertical handle bar near the door's free edge; a
    control panel fills the front beside the door."""
    t = 0.015
    shell = (0.85, 0.85, 0.85, 1)
    body = [Part((depth, width, t), (0, 0, t / 2), shell), Part((depth, width, t), (0, 0, height - t / 2), shell),
            Part((depth, t, height), (0, width / 2 - t / 2, height / 2), shell),
            Part((depth, t, height), (0, -width / 2 + t / 2, height / 2), shell),
            Part((t, width, height), (-depth / 2 + t / 2, 0, height / 2), shell),
            Part((t, width - door_width, height), (depth / 2 - t / 2, door_width / 2, height / 2),
                 (0.2, 0.2, 0.2, 1))]                                                   # control panel
    glass = (0.1, 0.1, 0.12, 1)
    door = [Part((0.02, door_width, height - 0.01), (0.01, door_width / 2, 0), glass),
            Part((MICROWAVE_HANDLE[1], 0.012, 0.012), (0.02 + MICROWAVE_HANDLE[1] / 2, door_width - 0.04, 0.05),
                 _METAL),
            Part((MICROWAVE_HANDLE[1], 0.012, 0.012), (0.02 + MICROWAVE_HANDLE[1] / 2, door_width - 0.04, -0.05),
                 _METAL),
            Part((MICROWAVE_HANDLE[0], 0.14), (0.02 + MICROWAVE_HANDLE[1], door_width - 0.04, 0), _METAL,
                 cylinder=True)]
    return _robot('microwave', _link('base', body, 0.0) + _link('door_link', door, 0.4)
                  + _joint('door', 'revolute', 'base', 'door_link', (depth / 2, -width / 2, height / 2),
                           axis=(0, 0, -1), limits=(0.0, 2.0)))


def oven(depth=0.34, width=0.40, height=0.34, door_height=OVEN_DOOR_HEIGHT) -> str:
    """An oven: joint `door` hinged along the bottom of the front, falling open towards +x
    (+), with a handle bar along y near its top. The door starts 10 cm up, so the hand
    holding the pulled-down handle stays clear of the table."""
    t = 0.015
    shell = (0.75, 0.75, 0.78, 1)
    bottom = 0.10
    body = [Part((depth, width, bottom), (0, 0, bottom / 2), shell),
            Part((depth, width, t), (0, 0, height - t / 2), shell),
            Part((depth, t, height), (0, width / 2 - t / 2, height / 2), shell),
            Part((depth, t, height), (0, -width / 2 + t / 2, height / 2), shell),
            Part((t, width, height), (-depth / 2 + t / 2, 0, height / 2), shell),
            Part((t, width, height - bottom - door_height), (depth / 2 - t / 2, 0, (height + bottom + door_height) / 2),
                 (0.2, 0.2, 0.2, 1))]                                                    # control strip
    door = [Part((0.02, width - 0.02, door_height), (0.01, 0, door_height / 2), (0.1, 0.1, 0.12, 1)),
            Part((OVEN_HANDLE[0], width - 0.12), (0.02 + OVEN_HANDLE[1], 0, door_height - 0.03), _METAL,
                 cylinder=True, rpy=(1.5708, 0, 0))]
    door += [Part((OVEN_HANDLE[1], 0.012, 0.012), (0.02 + OVEN_HANDLE[1] / 2, y, door_height - 0.03), _METAL)
             for y in (width / 2 - 0.08, -width / 2 + 0.08)]
    return _robot('oven', _link('base', body, 0.0) + _link('door_link', door, 0.5)
                  + _joint('door', 'revolute', 'base', 'door_link', (depth / 2, 0, bottom), axis=(0, 1, 0),
                           limits=(0.0, 1.65)))


def knife_block(length=0.16) -> str:
    """A narrow wooden rail the knife lies on, 5 cm high, along y: narrow enough for open fingers
    to reach past its top either side."""
    return _robot('knife_block', _link('base', [Part((0.03, length, KNIFE_BLOCK_HEIGHT),
                                                     (0, 0, KNIFE_BLOCK_HEIGHT / 2), (0.3, 0.18, 0.1, 1))], 0.0))


def chopping_board() -> str:
    return _robot('chopping_board', _link('base', [Part(CHOPPING_BOARD, (0, 0, CHOPPING_BOARD[2] / 2),
                                                        (0.8, 0.65, 0.45, 1))], 0.0))


def knife() -> str:
    """A free knife along +y, its frame at the centre of the handle, where its mass is: it lies
    on the handle, the blade held level."""
    handle = KNIFE_HANDLE
    return _robot('knife', _link('base', [
        Part(handle, (0, 0, 0), (0.1, 0.1, 0.1, 1)),
        Part((0.026, 0.16, 0.003), (0, handle[1] / 2 + 0.08, 0), _METAL)], 0.12))
