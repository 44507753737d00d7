"""Pure-numpy reader for OpenVDB (``.vdb``) files: scalar float grids to dense arrays.

By concept: the file (header, grid table, metadata, transforms; :mod:`~nrc.volume.vdb.reader`), bounds-checked
reads (:mod:`~nrc.volume.vdb.stream`), the tree (:mod:`~nrc.volume.vdb.tree`), its codecs
(:mod:`~nrc.volume.vdb.codecs`) and the dense array (:mod:`~nrc.volume.vdb.dense`).

Conventions:

* :func:`read_vdb` returns ``D`` of shape ``(nx, ny, nz)``, dtype float32, over the grid's *active*
  index-space bounding box ``[xmin, xmax] x [ymin, ymax] x [zmin, zmax]`` (inclusive), with
  ``D[i - xmin, j - ymin, k - zmin]`` the value of voxel ``(i, j, k)``: ``i`` runs along index x,
  ``j`` along y, ``k`` along z. Active tiles fill their whole region (8^3, 128^3 or 4096^3 voxels)
  clipped to that box. Inactive voxels are the grid's background value (0 for density grids). A grid
  with no active voxel gives a ``(0, 0, 0)`` array. The grid's transform (voxel size, placement in
  world space) is not applied.
* Grids are named as in the file; ``grid=None`` takes the first scalar float grid.

Supported: file format versions 220 to 224 (224 is the current one), grids of type
``Tree_float_5_4_3``, half-float storage, active tiles at every level, the codecs none, zip and
blosc (blosc through the optional ``blosc`` package), all per-node mask-compression schemes,
several grids per file, and instanced grids (which share their parent's tree). Not supported:
other value types (double, half, vector, integer, bool, point grids) and tree configurations,
files written to a stream without grid offsets, dense boxes of more than 2^30 voxels. Every
failure - a missing, truncated, corrupted or unsupported file - raises
:class:`~nrc.errors.VDBError` naming the file and the problem.
"""

from nrc.volume.vdb.reader import VDBGrid, list_vdb_grids, read_vdb, read_vdb_grid

__all__ = ["VDBGrid", "list_vdb_grids", "read_vdb", "read_vdb_grid"]
