"""One image in, a position and a heading out (localize.py, `geoloc serve`)."""

from geoloc.apps.localize.localizer import Localizer
from geoloc.data.io import read_rgb as read_street  # an image file as Localizer.localize takes it, as localize.py reads

__all__ = ["Localizer", "read_street"]
