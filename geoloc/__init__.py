"""geoloc: place recognition by image retrieval.

Two published methods on one small training engine:
- cross-view geo-localization with a multi-scale attention encoder (``geoloc.tasks.crossview``);
- place recognition in dynamic scenes, MMDIP (``geoloc.tasks.mmdip``).
"""

__version__ = "0.1.0"
