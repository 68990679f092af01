"""Reading meshes and scenes (anything trimesh reads), with a cache of parsed meshes.

Trees are read and written by :mod:`jaxbvh.tree.interchange`; :func:`load_any` reads
either a mesh or a tree file.
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

__all__ = ["TREE_SUFFIXES", "Mesh", "MeshError", "TreeFile", "boxes_in_frame", "bundled_mesh_path",
           "load_any", "load_mesh", "mesh_cache_folder", "use_mesh_cache"]
