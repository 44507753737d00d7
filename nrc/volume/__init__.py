"""Volumes: density grids, their loaders (OpenVDB, npz, procedural) and brick majorants."""

from nrc.volume.box import Box
from nrc.volume.grid import CellField, DensityGrid
from nrc.volume.majorant import MajorantGrid
from nrc.volume.npz import read_npz
from nrc.volume.procedural import procedural_cloud
from nrc.volume.vdb import read_vdb

__all__ = [
    "Box", "CellField", "DensityGrid", "MajorantGrid",
    "read_npz", "procedural_cloud", "read_vdb",
]
