"""Terrain: the DEM grid type, raster I/O, slope/normal/curvature fields, synthetic terrains, releases."""
from .fields import (
    curvature,
    gradient,
    hillshade,
    plan_curvature,
    profile_curvature,
    second_derivatives,
    slope,
    slope_deg,
    unit_normal,
)
from .grid import DEM, TerrainError
from .io import read_asc, read_dem, read_geotiff, read_raster, read_raster_like, write_asc, write_geotiff, write_raster
from .synthetic import (
    SYNTHETIC_TERRAINS,
    SyntheticCase,
    bondo_like,
    bowl,
    channel_with_bends,
    inclined_plane,
    parabola,
    release_from_raster,
    release_from_shape,
    thalweg_length,
)

__all__ = [
    "DEM", "TerrainError",
    "read_asc", "write_asc", "read_geotiff", "write_geotiff", "read_raster", "read_dem", "write_raster",
    "read_raster_like",
    "gradient", "slope", "slope_deg", "unit_normal", "second_derivatives", "curvature",
    "profile_curvature", "plan_curvature", "hillshade",
    "SyntheticCase", "inclined_plane", "parabola", "bowl", "channel_with_bends", "bondo_like",
    "release_from_shape", "release_from_raster", "thalweg_length", "SYNTHETIC_TERRAINS",
]
