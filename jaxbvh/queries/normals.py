"""Angle-weighted pseudonormals of a triangle mesh, for signed closest-point distances (NumPy, host).

Bærentzen and Aanæs 2005 ("Signed distance computation using the angle weighted
pseudonormal"): for a closed, consistently oriented manifold mesh, the sign of
``(p - q) . n`` is the inside/outside sign of ``p``, where ``q`` is the closest point on
the mesh and ``n`` the pseudonormal of the feature ``q`` lies on: the face normal in a
face's interior, the sum of the two adjacent face normals on an edge, and at a vertex the
sum of the incident face normals weighted by the angle each face makes there. Computed
once on the host; the query (:func:`jaxbvh.queries.closest_point`) only looks one up.

Vertices are welded by exact position (a triangle soup such as ``Mesh.local_triangles()``
shares corners by value), edges by their two welded vertices. Degenerate triangles (zero
area) add nothing. On an open mesh or a non-manifold edge the sign near the border or the
edge is not meaningful.
"""

from __future__ import annotations

import numpy as np


def pseudonormals(triangles) -> np.ndarray:
    """Pseudonormals [T, 7, 3] (float64, not normalised; only their sign matters) of
    ``triangles`` [T, 3, 3], one per feature in the order of
    :data:`jaxbvh.queries.geometry.FEATURES`: face, edges ab, bc, ca, vertices a, b, c."""
    tri = np.asarray(triangles, np.float64)
    t = tri.shape[0]
    corners = tri.reshape(-1, 3)
    _, vid = np.unique(corners, axis=0, return_inverse=True)
    vid = vid.reshape(t, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    unit = np.where(length > 0, normal / np.where(length > 0, length, 1), 0)

    # vertices: angle-weighted sums of the unit face normals
    angles = np.zeros((t, 3))
    for i in range(3):
        e1 = tri[:, (i + 1) % 3] - tri[:, i]
        e2 = tri[:, (i + 2) % 3] - tri[:, i]
        n1, n2 = np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1)
        ok = (n1 > 0) & (n2 > 0)
        cos = np.sum(e1 * e2, axis=1) / np.where(ok, n1 * n2, 1)
        angles[:, i] = np.where(ok, np.arccos(np.clip(cos, -1, 1)), 0)
    vertex = np.zeros((vid.max() + 1 if t else 0, 3))
    for i in range(3):
        np.add.at(vertex, vid[:, i], angles[:, i, None] * unit)

    # edges: sums of the unit normals of the faces that share them (undirected)
    ends = np.stack([vid[:, [0, 1]], vid[:, [1, 2]], vid[:, [2, 0]]], axis=1)  # [T, 3, 2]
    keys = np.sort(ends, axis=2).reshape(-1, 2)
    _, eid = np.unique(keys, axis=0, return_inverse=True)
    eid = eid.reshape(t, 3)
    edge = np.zeros((eid.max() + 1 if t else 0, 3))
    for i in range(3):
        np.add.at(edge, eid[:, i], unit)

    out = np.empty((t, 7, 3))
    out[:, 0] = unit
    out[:, 1:4] = edge[eid]
    out[:, 4:7] = vertex[vid]
    return out
