"""Procedural 2.5D world renderer: synthetic cross-view pairs and dynamic/static street views.

    generate(layout, out, train, val, seed=0, preset=None, workers=1, **overrides) -> Path
    ensure_dataset(layout, root, preset, train, val, seed=0, workers=1, **overrides) -> Path

Layouts: 'cvusa', 'cvact', 'vigor', 'u1652' (the real datasets' trees) and 'dynamic' (docs/dynamic_layout.md).
See docs/synthetic.md.
"""
from .appearance import AppearanceGap
from .classes import ALL_CLASSES, STATIC_CLASSES
from .world_config import LAYOUTS, PRESETS, SynthConfig
from .generate import MARKER, VERSION, DatasetMismatchError, default_cache, ensure_dataset, generate
from .geometry import tile_geometry

__all__ = ["generate", "ensure_dataset", "SynthConfig", "AppearanceGap", "PRESETS", "LAYOUTS", "MARKER", "VERSION",
           "DatasetMismatchError", "default_cache", "STATIC_CLASSES", "ALL_CLASSES", "tile_geometry"]
