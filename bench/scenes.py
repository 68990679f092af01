"""Procedural bench scenes: an architectural interior (issue 40, part 5).

    python bench/scenes.py interior -o /tmp/interior.obj          # seed 0, the bench's scene
    python bench/scenes.py interior --seed 3 --floors 3 -o x.obj

:func:`interior` builds a house of ``floors`` storeys of ``rooms_x`` x ``rooms_z`` rooms:
walls with door and window openings (thick boxes cut around the openings: long thin
triangles), floors of coplanar tiles, one large two-triangle ceiling per room, window
panes and frames, a staircase between storeys, and furniture in every room (a table,
chairs, a shelf, a hanging lamp with a round shade, a floor lamp): thin legs and cords,
large and small triangles, many coplanar faces -- the kind of scene where leaves of
several primitives pay (issue 40). Units: metres, y up. Deterministic from ``seed``
(``numpy.random.default_rng``); the default is about 50,000 triangles.

:func:`bench_mesh_path` writes the bench's scene once per process (an OBJ in a temp
folder, through :func:`jaxbvh.files.atomic_write`) so bench scripts and tinybvh's harness
read the same file; :data:`PROCEDURAL` names the procedural inputs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from jaxbvh.files import atomic_write  # noqa: E402

#: bench input name -> keyword arguments of :func:`interior`
PROCEDURAL = {"interior": {"seed": 0}}


class _Builder:
    """Collects triangles as (vertices [v, 3], faces [f, 3]) parts."""

    def __init__(self):
        self.parts: list[tuple[np.ndarray, np.ndarray]] = []

    def add(self, vertices, faces):
        self.parts.append((np.asarray(vertices, np.float64), np.asarray(faces, np.int64)))

    def box(self, lo, hi):
        """An axis-aligned box [lo, hi] (metres): 12 triangles."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        if np.any(hi <= lo):
            return
        corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
        faces = [(0, 2, 3), (0, 3, 1), (4, 5, 7), (4, 7, 6), (0, 1, 5), (0, 5, 4),
                 (2, 6, 7), (2, 7, 3), (0, 4, 6), (0, 6, 2), (1, 3, 7), (1, 7, 5)]
        self.add(corners, faces)

    def quad(self, a, b, c, d):
        """The quad a b c d (two triangles)."""
        self.add([a, b, c, d], [(0, 1, 2), (0, 2, 3)])

    def grid_y(self, x0, x1, z0, z1, y, nx, nz):
        """A horizontal grid of ``nx`` x ``nz`` coplanar quads at height ``y`` (floor tiles)."""
        xs, zs = np.linspace(x0, x1, nx + 1), np.linspace(z0, z1, nz + 1)
        gx, gz = np.meshgrid(xs, zs, indexing="ij")
        v = np.stack([gx.ravel(), np.full(gx.size, y), gz.ravel()], 1)
        i = np.arange(nx)[:, None] * (nz + 1) + np.arange(nz)[None, :]
        i = i.ravel()
        faces = np.concatenate([np.stack([i, i + 1, i + nz + 2], 1), np.stack([i, i + nz + 2, i + nz + 1], 1)])
        self.add(v, faces)

    def frustum(self, base, r0, r1, height, sides, caps=True):
        """A vertical cylinder or cone frustum from ``base`` (x, y, z) up ``height``."""
        t = np.linspace(0, 2 * np.pi, sides, endpoint=False)
        ring = np.stack([np.cos(t), np.zeros(sides), np.sin(t)], 1)
        b = np.asarray(base, float)
        v = np.concatenate([b + r0 * ring, b + r1 * ring + [0, height, 0], [b, b + [0, height, 0]]])
        j = np.arange(sides)
        k = (j + 1) % sides
        faces = [np.stack([j, k, sides + k], 1), np.stack([j, sides + k, sides + j], 1)]
        if caps:
            faces += [np.stack([np.full(sides, 2 * sides), k, j], 1),
                      np.stack([np.full(sides, 2 * sides + 1), sides + j, sides + k], 1)]
        self.add(v, np.concatenate(faces))

    def sphere(self, centre, radius, rings, segments):
        """A UV sphere: many small triangles."""
        phi = np.linspace(0, np.pi, rings + 1)
        th = np.linspace(0, 2 * np.pi, segments, endpoint=False)
        p, t = np.meshgrid(phi, th, indexing="ij")
        v = np.stack([np.sin(p) * np.cos(t), np.cos(p), np.sin(p) * np.sin(t)], -1).reshape(-1, 3)
        v = np.asarray(centre, float) + radius * v
        r = np.arange(rings)[:, None]
        s = np.arange(segments)[None, :]
        a = r * segments + s
        b = r * segments + (s + 1) % segments
        faces = np.concatenate([np.stack([a, b, b + segments], -1).reshape(-1, 3),
                                np.stack([a, b + segments, a + segments], -1).reshape(-1, 3)])
        tri = v[faces]
        keep = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) > 0
        self.add(v, faces[keep])  # the poles' rings of zero-area triangles dropped

    def mesh(self):
        vs, fs, offset = [], [], 0
        for v, f in self.parts:
            vs.append(v)
            fs.append(f + offset)
            offset += v.shape[0]
        return np.concatenate(vs), np.concatenate(fs).astype(np.int64)


def _wall(b: _Builder, axis: int, at: float, a0: float, a1: float, y0: float, height: float,
          thick: float, openings):
    """A wall on the plane ``x = at`` (axis 0) or ``z = at`` (axis 2) from ``a0`` to ``a1``
    along the other horizontal axis, cut around ``openings`` [(centre, width, bottom, top)]
    (doors and windows); window openings get a frame and a pane."""

    def put(u0, u1, v0, v1, t0, t1):
        lo, hi = [0.0] * 3, [0.0] * 3
        other = 2 - axis
        lo[axis], hi[axis] = t0, t1
        lo[other], hi[other] = u0, u1
        lo[1], hi[1] = v0, v1
        b.box(lo, hi)

    t0, t1 = at - thick / 2, at + thick / 2
    u = a0
    for centre, width, bottom, top in sorted(openings):
        o0, o1 = centre - width / 2, centre + width / 2
        put(u, o0, y0, y0 + height, t0, t1)           # the full-height piece before it
        put(o0, o1, y0 + top, y0 + height, t0, t1)    # lintel
        put(o0, o1, y0, y0 + bottom, t0, t1)          # parapet (none for a door)
        if bottom > 0:  # a window: frame bars and a pane in the wall's middle plane
            f = 0.05
            put(o0, o1, y0 + bottom, y0 + bottom + f, t0, t1)
            put(o0, o1, y0 + top - f, y0 + top, t0, t1)
            put(o0, o0 + f, y0 + bottom, y0 + top, t0, t1)
            put(o1 - f, o1, y0 + bottom, y0 + top, t0, t1)
            put(centre - f / 2, centre + f / 2, y0 + bottom, y0 + top, t0, t1)  # mullion
            put(o0, o1, y0 + bottom, y0 + top, at - 0.005, at + 0.005)        # glass
        u = o1
    put(u, a1, y0, y0 + height, t0, t1)


def _table(b, rng, x, z, y, w, d, h):
    b.box([x - w / 2, y + h - 0.04, z - d / 2], [x + w / 2, y + h, z + d / 2])
    for sx in (-1, 1):
        for sz in (-1, 1):
            b.frustum([x + sx * (w / 2 - 0.06), y, z + sz * (d / 2 - 0.06)], 0.025, 0.02, h - 0.04, 10)


def _chair(b, rng, x, z, y, facing):
    s = 0.44
    b.box([x - s / 2, y + 0.43, z - s / 2], [x + s / 2, y + 0.47, z + s / 2])
    for sx in (-1, 1):
        for sz in (-1, 1):
            b.frustum([x + sx * (s / 2 - 0.03), y, z + sz * (s / 2 - 0.03)], 0.015, 0.015, 0.43, 8)
    # the back on the side away from the table: thin slats
    dx, dz = facing
    for k in range(5):
        off = -s / 2 + 0.04 + k * (s - 0.08) / 4
        if dx:
            bx = x - dx * (s / 2 - 0.015)
            b.box([bx - 0.015, y + 0.47, z + off - 0.012], [bx + 0.015, y + 0.95, z + off + 0.012])
        else:
            bz = z - dz * (s / 2 - 0.015)
            b.box([x + off - 0.012, y + 0.47, bz - 0.015], [x + off + 0.012, y + 0.95, bz + 0.015])


def _shelf(b, rng, x0, x1, z0, z1, y, height, boards):
    """A bookshelf: side panels, coplanar boards, books (small boxes) on each board."""
    b.box([x0, y, z0], [x0 + 0.02, y + height, z1])
    b.box([x1 - 0.02, y, z0], [x1, y + height, z1])
    for k in range(boards):
        by = y + k * height / (boards - 1) if boards > 1 else y
        b.box([x0 + 0.02, by, z0], [x1 - 0.02, by + 0.02, z1])
        if k < boards - 1:
            bx = x0 + 0.03
            while bx < x1 - 0.06:
                bw = rng.uniform(0.03, 0.07)
                bh = rng.uniform(0.15, min(0.3, height / (boards - 1) - 0.04))
                b.box([bx, by + 0.02, z0 + 0.01], [bx + bw, by + 0.02 + bh, z1 - 0.02])
                bx += bw + rng.uniform(0.0, 0.01)


def _lamps(b, rng, cx, cz, y_floor, y_ceiling, corner):
    # hanging lamp: a thin cord and a round shade
    b.frustum([cx, y_ceiling - 0.9, cz], 0.004, 0.004, 0.9, 6, caps=False)
    b.sphere([cx, y_ceiling - 1.0, cz], 0.15, 12, 20)
    # floor lamp in a corner: base, pole, cone shade
    fx, fz = corner
    b.frustum([fx, y_floor, fz], 0.15, 0.15, 0.03, 16)
    b.frustum([fx, y_floor + 0.03, fz], 0.012, 0.012, 1.5, 8)
    b.frustum([fx, y_floor + 1.45, fz], 0.25, 0.12, 0.3, 20, caps=False)


def _stairs(b, x0, x1, z0, y0, rise, steps, run):
    """A straight staircase along +z from (x0..x1, z0) up ``rise``: step boxes, stringers, rails."""
    h = rise / steps
    for k in range(steps):
        b.box([x0, y0 + k * h, z0 + k * run], [x1, y0 + (k + 1) * h, z0 + (k + 1) * run])
    for x in (x0 - 0.04, x1):  # handrail posts: thin and tall
        for k in range(0, steps, 2):
            b.box([x, y0 + (k + 1) * h, z0 + k * run + run / 2 - 0.015],
                  [x + 0.04, y0 + (k + 1) * h + 0.9, z0 + k * run + run / 2 + 0.015])
        # a sloped rail: a long thin quad strip (two quads)
        a = np.array([x, y0 + h + 0.9, z0 + run / 2])
        c = np.array([x, y0 + rise + 0.9, z0 + (steps - 0.5) * run])
        b.quad(a, a + [0.04, 0, 0], c + [0.04, 0, 0], c)
        b.quad(a + [0, 0.05, 0], c + [0, 0.05, 0], c + [0.04, 0.05, 0], a + [0.04, 0.05, 0])


def interior(seed: int = 0, floors: int = 2, rooms_x: int = 3, rooms_z: int = 3, room: float = 5.0,
             height: float = 3.0, tiles: int = 10):
    """An architectural interior: ``vertices`` float64 [v, 3] (metres, y up), ``faces``
    int64 [f, 3]. ``floors`` storeys of ``rooms_x`` x ``rooms_z`` rooms of ``room`` metres
    square and ``height`` metres; each room's floor is ``tiles`` x ``tiles`` coplanar
    quads. Deterministic from ``seed``."""
    rng = np.random.default_rng(seed)
    b = _Builder()
    slab, wall = 0.2, 0.15
    width, depth = rooms_x * room, rooms_z * room
    storey = height + slab
    for f in range(floors):
        y = f * storey
        yf = y + slab  # floor surface
        b.box([0, y, 0], [width, yf, depth])  # the slab: two huge triangles per face
        for i in range(rooms_x):
            for k in range(rooms_z):
                x0, z0 = i * room, k * room
                b.grid_y(x0, x0 + room, z0, z0 + room, yf, tiles, tiles)
                # one large ceiling quad per room, just under the next slab
                yc = yf + height - 0.01
                b.quad([x0, yc, z0], [x0 + room, yc, z0], [x0 + room, yc, z0 + room], [x0, yc, z0 + room])
        # walls: x = const and z = const lines; inner ones with doors, outer ones with windows
        for i in range(rooms_x + 1):
            outer = i in (0, rooms_x)
            for k in range(rooms_z):
                c = k * room + room / 2 + rng.uniform(-1.0, 1.0)
                opening = (c, 1.4, 0.9, 2.2) if outer else (c, 0.9, 0.0, 2.1)
                _wall(b, 0, i * room, k * room, (k + 1) * room, yf, height, wall, [opening])
        for k in range(rooms_z + 1):
            outer = k in (0, rooms_z)
            for i in range(rooms_x):
                c = i * room + room / 2 + rng.uniform(-1.0, 1.0)
                opening = (c, 1.4, 0.9, 2.2) if outer else (c, 0.9, 0.0, 2.1)
                _wall(b, 2, k * room, i * room, (i + 1) * room, yf, height, wall, [opening])
        # furniture
        for i in range(rooms_x):
            for k in range(rooms_z):
                x0, z0 = i * room, k * room
                if f + 1 < floors and i == 0 and k == 0:
                    _stairs(b, x0 + 0.5, x0 + 1.5, z0 + 0.4, yf, storey, 16, 0.27)
                    continue
                cx, cz = x0 + room / 2 + rng.uniform(-0.5, 0.5), z0 + room / 2 + rng.uniform(-0.5, 0.5)
                tw, td = rng.uniform(1.2, 2.0), rng.uniform(0.8, 1.0)
                _table(b, rng, cx, cz, yf, tw, td, 0.75)
                for side in (-1, 1):
                    for s in range(int(rng.integers(1, 4))):
                        off = (s - 1) * 0.55
                        _chair(b, rng, cx + off, cz + side * (td / 2 + 0.3), yf, (0, -side))
                    _chair(b, rng, cx + side * (tw / 2 + 0.3), cz, yf, (-side, 0))
                _shelf(b, rng, x0 + 0.6, x0 + 1.8, z0 + room - 0.45, z0 + room - 0.12, yf, 2.0, 4)
                _lamps(b, rng, cx, cz, yf, yf + height, (x0 + room - 0.5, z0 + 0.5))
    b.box([-0.5, floors * storey, -0.5], [width + 0.5, floors * storey + 0.3, depth + 0.5])  # roof
    return b.mesh()


def write_obj(path, vertices, faces) -> None:
    """Write an OBJ (``v`` and ``f`` lines, 1-based) through :func:`jaxbvh.files.atomic_write`."""
    with atomic_write(path, "w") as out:
        out.write(f"# jaxbvh bench/scenes.py: {faces.shape[0]} triangles\n")
        np.savetxt(out, vertices, fmt="v %.6f %.6f %.6f")
        np.savetxt(out, faces + 1, fmt="f %d %d %d")


_WRITTEN: dict[str, Path] = {}


def bench_mesh_path(name: str, folder: str | Path | None = None) -> Path:
    """The OBJ of the procedural input ``name`` (:data:`PROCEDURAL`), written once per
    process into ``folder`` (default: a temporary folder)."""
    if name not in _WRITTEN:
        folder = Path(folder) if folder else Path(tempfile.mkdtemp(prefix="jaxbvh-scene-"))
        path = folder / f"{name}.obj"
        write_obj(path, *interior(**PROCEDURAL[name]))
        _WRITTEN[name] = path
    return _WRITTEN[name]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", choices=["interior"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--floors", type=int, default=2)
    parser.add_argument("--rooms-x", type=int, default=3)
    parser.add_argument("--rooms-z", type=int, default=3)
    parser.add_argument("-o", "--output", required=True)
    args = parser.parse_args(argv)
    v, f = interior(args.seed, args.floors, args.rooms_x, args.rooms_z)
    write_obj(args.output, v, f)
    print(f"{args.output}: {f.shape[0]:,} triangles, {v.shape[0]:,} vertices", file=sys.stderr)


if __name__ == "__main__":
    main()
