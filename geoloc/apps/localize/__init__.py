"""One image in, a position and a heading out (localize.py, `geoloc serve`)."""

from geoloc.apps.localize.localizer import Localizer, read_street

__all__ = ["Localizer", "read_street"]
