"""`geoloc robustness`: one checkpoint under every test condition the field reports (conditions.py), written as one
Markdown and one JSON table (command.py)."""

from geoloc.apps.robustness.command import USAGE, main, robustness

__all__ = ["USAGE", "main", "robustness"]
