"""`geoloc serve`: a FastAPI query service over a loaded localizer (app.py); needs the `serve` extra."""

from geoloc.apps.serve.app import create_app

__all__ = ["create_app"]
