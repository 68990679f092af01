"""Reading meshes and scenes (anything trimesh reads), with a cache of parsed meshes.

Trees are read and written by :mod:`jaxbvh.tree.interchange`; :func:`load_any` reads
either a mesh or a tree file. :func:`export_tinybvh` writes a tree and its triangles as
the node file C++ tracers load into tinybvh (:mod:`jaxbvh.io.tinybvh`), and
:func:`read_tinybvh` reads one back.
"""

from jaxbvh.io.meshes import (
                              TREE_SUFFIXES,
                              Mesh,
                              MeshError,
                              TreeFile,
                              boxes_in_frame,
                              bundled_mesh_path,
                              load_any,
                              load_mesh,
                              mesh_cache_folder,
                              use_mesh_cache,
)
from jaxbvh.io.tinybvh import TinyBVHFile, export_tinybvh, read_tinybvh

__all__ = ["TREE_SUFFIXES", "TinyBVHFile", "export_tinybvh", "read_tinybvh", "Mesh", "MeshError", "TreeFile", "boxes_in_frame", "bundled_mesh_path",
           "load_any", "load_mesh", "mesh_cache_folder", "use_mesh_cache"]
