"""Mesh files cut into chunks of one capacity bucket each: :func:`chunk_items`.

A chunk is one task of a run of files (:mod:`jaxbvh.batch.runs`): a worker builds its
meshes with :func:`jaxbvh.batch.build`, one compiled call per capacity group in it. A
chunk whose files share one capacity bucket (:func:`jaxbvh.tree.layout.capacity_bucket`
of the triangle count) is one call, of one program the worker keeps for every later
chunk of that bucket; a chunk that mixes buckets runs several smaller calls, each a
program of its own row count that the worker must trace, lower and load (from the
compile cache, or compile) again. Those per-program costs are what a worker spends most
of a small mesh's time on (``bench/bench_cluster.py``), so the driver sorts the files into
buckets *before* cutting chunks.

Counts. The driver cannot load every mesh (at 10^6 files that would be the whole job on
one host), so it *estimates* each file's triangles from what is cheap to read
(:func:`triangle_estimate`): the face count in a PLY or OFF header, the count of a binary
STL, the face lines of an OBJ or the facets of an ASCII STL (a scan of the bytes, no
parsing of numbers). Other formats (glTF, GLB) have no estimate and are chunked among
themselves by file size. An estimate only places a file: a worker builds whatever its
chunk holds, grouped by the real counts, so a wrong estimate costs a call, never a tree.

Rule: the files of one bucket are cut, in input order, into chunks of ``chunk_files``
(the last one shorter), so a bucket's calls have at most two row counts; the chunks are
ordered by estimated work (capacity times files), largest first, so the last tasks of a
run are short ones and no worker is left with a big one while the others idle.
"""

from __future__ import annotations

import os
import re

from jaxbvh.tree.layout import capacity_bucket

#: bytes of a PLY or OFF header read to find the face count (headers are a few hundred)
HEADER_BYTES = 1 << 16
#: a line of an OBJ that starts a face (``f`` then blanks), anywhere in the file
_OBJ_FACE = re.compile(rb"^[ \t]*f[ \t]+([^\r\n]*)", re.MULTILINE)
_PLY_FACES = re.compile(rb"^element[ \t]+face[ \t]+(\d+)", re.MULTILINE)


def _obj_triangles(data: bytes) -> int:
    """Triangles of an OBJ's face lines: a face of k corners is k - 2 triangles (a fan).

    The usual file has only triangles; the first face line says so, and then the count of
    face lines is the answer, without a pass per line."""
    first = _OBJ_FACE.search(data)
    if first is None:
        return 0
    if len(first.group(1).split()) == 3:
        return data.count(b"\nf ") + data.count(b"\nf\t") + (1 if data[:2] in (b"f ", b"f\t") else 0)
    return sum(max(len(m.group(1).split()) - 2, 0) for m in _OBJ_FACE.finditer(data))


def _off_faces(head: bytes) -> int | None:
    lines = [ln.split(b"#")[0].strip() for ln in head.splitlines()]
    words = [w for ln in lines if ln for w in ln.split()]
    if not words or not words[0].endswith(b"OFF"):
        return None
    try:
        return int(words[2])  # OFF, vertices, faces, edges
    except (IndexError, ValueError):
        return None


def triangle_estimate(path) -> int | None:
    """An estimate of the triangles :func:`jaxbvh.io.load_mesh` finds in ``path`` (module
    docstring), or None where the format gives none cheaply or the file cannot be read.

    PLY and OFF: the header's face count (polygons count once). STL: the binary header's
    count, or the facets of an ASCII file. OBJ: its face lines, each ``corners - 2``.
    """
    suffix = os.path.splitext(str(path))[1].lower()
    try:
        if suffix == ".obj":
            with open(path, "rb") as f:
                return _obj_triangles(f.read())
        if suffix == ".stl":
            size = os.path.getsize(path)
            with open(path, "rb") as f:
                head = f.read(84)
                if len(head) == 84 and 84 + 50 * int.from_bytes(head[80:84], "little") == size:
                    return int.from_bytes(head[80:84], "little")
                return (head + f.read()).count(b"endfacet")
        if suffix in (".ply", ".off"):
            with open(path, "rb") as f:
                head = f.read(HEADER_BYTES)
            if suffix == ".off":
                return _off_faces(head)
            found = _PLY_FACES.search(head.split(b"end_header")[0])
            return int(found.group(1)) if found else None
    except OSError:
        return None
    return None


def chunk_items(items, chunk_files: int, estimate=triangle_estimate) -> list[list]:
    """``items`` (``[(path, name), ...]``) cut into chunks of at most ``chunk_files``, each
    of one estimated capacity bucket, largest estimated work first (module docstring).

    ``estimate(path) -> int | None``: a file's triangles (None: unknown; those files are
    chunked among themselves, by file size).
    """
    if chunk_files < 1:
        raise ValueError(f"chunk_files must be >= 1, got {chunk_files}")
    buckets: dict = {}
    unknown = []
    for item in items:
        count = estimate(item[0])
        if count is None:
            unknown.append(item)
        else:
            buckets.setdefault(capacity_bucket(max(int(count), 1)), []).append(item)
    cut = []  # (estimated work, order made, chunk)
    for capacity, members in buckets.items():
        for k in range(0, len(members), chunk_files):
            part = members[k:k + chunk_files]
            cut.append((capacity * len(part), len(cut), part))

    def size(item):
        try:
            return os.path.getsize(item[0])
        except OSError:
            return -1

    cut.sort(key=lambda c: (-c[0], c[1]))
    # files of no estimate: by size, the largest chunks first, all before the estimated
    # ones (their work is unknown: better early than as a long tail)
    unknown.sort(key=size, reverse=True)
    return [unknown[k:k + chunk_files] for k in range(0, len(unknown), chunk_files)] + [part for _, _, part in cut]


__all__ = ["chunk_items", "triangle_estimate", "HEADER_BYTES"]
