"""Refiners: fine-grained (metric) localisation inside a tile. Given a street query and an aerial tile that covers
it, a refiner says where in the tile the camera is and which way it looks, as a probability over positions and
heading bins (`Refinement`). This package declares the `refiner` kind (config section `refiner`) and registers the
built-in `correlation` (correlation.py); a plug-in registers its own the same way (docs/extending.md)."""

from geoloc import registry
from geoloc.models.refiners.refinement import Refinement, check_refiner

registry.declare("refiner", section="refiner")

from geoloc.models.refiners import correlation  # noqa: E402,F401  (registers correlation)

__all__ = ["Refinement", "check_refiner"]
