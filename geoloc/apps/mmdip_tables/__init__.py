"""The MMDIP paper's Tables I-IV and figures on one dataset (tables.py), from one command (command.py)."""

from geoloc.apps.mmdip_tables.command import main

__all__ = ["main"]
