"""Isosurfaces of structured volumes (seed ch. 3-4): lossless min/max octree volumes, a
dense macrocell-grid baseline, exact trilinear cell intersection, level of detail and
time-varying sequences."""

from . import data
from ._bricks import BrickedVolume, SampledField, brick_volume, nearest_hits
from ._hierarchy import MacrocellGrid
from ._lod import LevelOfDetail, lod_for
from ._octree import OctreeVolume
from ._scene import VolumeIsosurface
from ._sequence import VolumeSequence

__all__ = ["OctreeVolume", "VolumeIsosurface", "MacrocellGrid", "VolumeSequence",
           "LevelOfDetail", "lod_for", "data", "BrickedVolume",
           "brick_volume", "nearest_hits", "SampledField"]
