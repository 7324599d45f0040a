"""Sequence localisation: a route's single-image answers (the top-k tiles of a saved gallery) and its odometry,
fused by a particle filter into each frame's position, heading and 95% region (docs/sequence.md)."""

from geoloc.sequence.estimate import FrameEstimate
from geoloc.sequence.extent import GalleryExtent
from geoloc.sequence.measurement import FrameAnswer
from geoloc.sequence.odometry import Motion, Odometry, read_odometry
from geoloc.sequence.particle_filter import FilterConfig, ParticleFilter, localize_route
from geoloc.sequence.simulation import SimulatedGallery, SimulatedRoute, SimulationConfig

__all__ = ["FilterConfig", "FrameAnswer", "FrameEstimate", "GalleryExtent", "Motion", "Odometry", "ParticleFilter",
           "SimulatedGallery", "SimulatedRoute", "SimulationConfig", "localize_route", "read_odometry"]
