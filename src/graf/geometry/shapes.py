"""Scene geometry generated from a config: a room (six quads) or open ground, and box objects.

Pure numpy; :mod:`graf.sim.tracer` turns it into Sionna RT meshes at run time (nothing is downloaded).
Walls, floor and ceiling are single flat surfaces whose radio material carries their thickness, as
Sionna RT models walls; furniture and buildings are closed boxes (each face with half the box's
smallest size as thickness unless given).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_BOX_FACES = np.array(
    [
        [0, 2, 3],
        [0, 3, 1],
        [4, 5, 7],
        [4, 7, 6],
        [0, 1, 5],
        [0, 5, 4],
        [2, 6, 7],
        [2, 7, 3],
        [0, 4, 6],
        [0, 6, 2],
        [1, 3, 7],
        [1, 7, 5],
    ],
    dtype=np.uint32,
)
_QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


@dataclass
class Surface:
    """A triangle mesh of one material (a wall, a floor): ``vertices [V, 3]``, ``faces [F, 3]``, ITU material, m."""

    name: str
    vertices: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3] uint32
    material: str  # ITU type
    thickness: float


@dataclass
class Box:
    """A piece of furniture: an axis-aligned box (m) turned by ``yaw_deg`` about the vertical."""

    name: str
    center: np.ndarray
    size: np.ndarray
    yaw_deg: float = 0.0

    def _rot(self) -> np.ndarray:
        t = np.deg2rad(self.yaw_deg)
        return np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])

    def vertices(self) -> np.ndarray:
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return (corners * self.size / 2) @ self._rot().T + self.center

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        local = (np.asarray(points) - self.center) @ self._rot()
        return np.all(np.abs(local) <= self.size / 2 + margin, axis=-1)


@dataclass
class SceneGeometry:
    """A scene's geometry for the ray tracer and the transmitters' placement: its surfaces, its boxes and bounds."""

    surfaces: list[Surface] = field(default_factory=list)
    boxes: list[Box] = field(default_factory=list)
    bounds: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))

    def inside_objects(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        mask = np.zeros(len(points), dtype=bool)
        for b in self.boxes:
            mask |= b.contains(points, margin)
        return mask


def _quad(name, corners, material, thickness) -> Surface:
    return Surface(name, np.asarray(corners, float), _QUAD_FACES.copy(), material, float(thickness))


def build_geometry(room: dict | None = None, ground: dict | None = None, objects: dict | None = None) -> SceneGeometry:
    """Neither ``room`` nor ``ground``: free space with only the objects (its bounds theirs).  ``room``: {size:
    [X, Y, Z], walls, floor, ceiling: ITU types, wall_thickness, floor_thickness, ceiling_thickness}, spanning
    [0, X] x [0, Y] x [0, Z].  ``ground``: {size: [X, Y], material, thickness} at z = 0 (open scenes, height from
    ``ground.height``).  ``objects``: name -> {material, center, size, yaw (deg), thickness}; a null entry is a
    removed object (layout variants)."""
    geo = SceneGeometry()
    if room is not None and ground is not None:
        raise ValueError("a simulated scene has a 'room' or a 'ground', not both")
    if room is not None:
        geo.surfaces += _room_surfaces(room)
        geo.bounds = np.array([[0, 0, 0], [float(v) for v in room["size"]]], float)
    elif ground is not None:
        X, Y = (float(v) for v in ground["size"])
        corners = [[0, 0, 0], [X, 0, 0], [X, Y, 0], [0, Y, 0]]
        material, thickness = ground.get("material", "medium_dry_ground"), ground.get("thickness", 1.0)
        geo.surfaces.append(_quad("ground", corners, material, thickness))
        geo.bounds = np.array([[0, 0, 0], [X, Y, float(ground.get("height", 10.0))]], float)
    for name, spec in sorted((objects or {}).items()):
        if spec is not None:
            box, surface = _object(name, spec)
            geo.boxes.append(box)
            geo.surfaces.append(surface)
    if room is None and ground is None and geo.boxes:  # free space: the objects' bounds
        v = np.vstack([b.vertices() for b in geo.boxes])
        geo.bounds = np.stack([v.min(0), v.max(0)])
    return geo


def _room_surfaces(room: dict) -> list[Surface]:
    """A room's floor, ceiling and four walls, spanning ``[0, X] x [0, Y] x [0, Z]`` (normals facing in)."""
    X, Y, Z = (float(v) for v in room["size"])
    wt = float(room.get("wall_thickness", 0.2))
    w = room.get("walls", "concrete")
    floor = (room.get("floor", "concrete"), room.get("floor_thickness", 0.2))
    ceiling = (room.get("ceiling", "ceiling_board"), room.get("ceiling_thickness", 0.05))
    return [
        _quad("floor", [[0, 0, 0], [X, 0, 0], [X, Y, 0], [0, Y, 0]], *floor),
        _quad("ceiling", [[0, 0, Z], [0, Y, Z], [X, Y, Z], [X, 0, Z]], *ceiling),
        _quad("wall_x0", [[0, 0, 0], [0, Y, 0], [0, Y, Z], [0, 0, Z]], w, wt),
        _quad("wall_x1", [[X, 0, 0], [X, 0, Z], [X, Y, Z], [X, Y, 0]], w, wt),
        _quad("wall_y0", [[0, 0, 0], [0, 0, Z], [X, 0, Z], [X, 0, 0]], w, wt),
        _quad("wall_y1", [[0, Y, 0], [X, Y, 0], [X, Y, Z], [0, Y, Z]], w, wt),
    ]


def _object(name: str, spec: dict) -> tuple[Box, Surface]:
    """An object's box and its surface, checked: a material, a centre and a size of 3 positive numbers."""
    for key in ("material", "center", "size"):
        if key not in spec:
            raise ValueError(f"object {name!r} has no {key!r}")
    box = Box(name, np.asarray(spec["center"], float), np.asarray(spec["size"], float), float(spec.get("yaw", 0.0)))
    if box.size.shape != (3,) or np.any(box.size <= 0):
        raise ValueError(f"object {name!r}: size must be 3 positive numbers, got {spec['size']}")
    thickness = spec.get("thickness") or float(box.size.min()) / 2
    return box, Surface(name, box.vertices(), _BOX_FACES.copy(), spec["material"], float(thickness))


def sample_positions(geo: SceneGeometry, count: int, low, high, seed: int, clearance: float = 0.05) -> np.ndarray:
    """``count`` transmitter positions drawn uniformly (seeded) in the box [low, high], keeping
    ``clearance`` metres away from every object (rejection sampling; deterministic for a seed)."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    if np.any(high <= low):
        raise ValueError(f"transmitter region is empty: min {low.tolist()} max {high.tolist()}")
    rng = np.random.default_rng(seed)
    out = np.zeros((0, 3))
    for _ in range(100):
        cand = rng.uniform(low, high, size=(max(2 * (count - len(out)), 64), 3))
        cand = cand[~geo.inside_objects(cand, clearance)]
        out = np.vstack([out, cand])[:count]
        if len(out) == count:
            return out
    raise ValueError(f"could not place {count} transmitters clear of objects in {low.tolist()}..{high.tolist()}")
