"""Generator settings and named presets.

A preset is a bundle of sizes for all three layouts plus default sample counts; keyword overrides replace single
fields. `SynthConfig` rejects unknown fields and bad values at construction, before any work starts.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from .appearance import AppearanceGap
from .styles import STYLES

LAYOUTS = ("cvusa", "cvact", "dynamic")


@dataclass(frozen=True)
class SynthConfig:
    aerial_size: int = 750  # aerial tile side, pixels (cvusa, cvact)
    pano_height: int = 224  # CVUSA-style horizon-band panorama (cvusa)
    pano_width: int = 1232
    sphere_height: int = 832  # full-sphere panorama (cvact)
    sphere_width: int = 1664
    view_size: int = 512  # square pinhole view (dynamic)
    fov_deg: float = 90.0
    cell_m: float = 0.3  # world grid cell
    tile_m: float = 144.0  # ground covered by the aerial tile (CVUSA's 750 px zoom-19 tiles: about 0.2 m/px)
    world_margin: float = 1.4  # world side = tile_m * world_margin, so the street views see past the tile
    camera_height: float = 2.2
    style: str = "mix"  # mix | urban | suburban | rural
    traffic: float = 1.0  # car / pedestrian density multiplier
    jitter_m: float = 2.0  # dynamic queries: position jitter
    jitter_yaw: float = 10.0  # dynamic queries: heading jitter, degrees
    gap_strength: float = 0.5  # appearance gap (see appearance.py); the next six override single controls
    sun_shift: float | None = None
    color_shift: float | None = None
    season_shift: float | None = None
    traffic_change: float | None = None
    noise_std: float | None = None
    jpeg_quality: int | None = None

    def __post_init__(self):
        # Coerce to the declared types, so 144 and 144.0 give the same marker (and the same dataset).
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None or isinstance(v, bool):
                continue
            kind = f.type if isinstance(f.type, str) else f.type.__name__
            try:
                if kind.startswith("int"):
                    if float(v) != int(v):
                        raise ValueError
                    object.__setattr__(self, f.name, int(v))
                elif kind.startswith("float"):
                    object.__setattr__(self, f.name, float(v))
            except (TypeError, ValueError):
                raise ValueError(f"{f.name} must be a number of type {kind}, got {v!r}") from None
        for name in ("aerial_size", "pano_height", "pano_width", "sphere_height", "sphere_width", "view_size"):
            if int(getattr(self, name)) < 8:
                raise ValueError(f"{name} must be at least 8 pixels, got {getattr(self, name)}")
        if self.cell_m <= 0 or self.tile_m <= 0 or self.world_margin < 1.0:
            raise ValueError("cell_m and tile_m must be positive and world_margin >= 1")
        if self.tile_m / self.cell_m < 16:
            raise ValueError(f"tile_m / cell_m = {self.tile_m / self.cell_m:.1f} cells is too coarse (need >= 16)")
        if self.style != "mix" and self.style not in STYLES:
            raise ValueError(f"style must be 'mix' or one of {STYLES}, got {self.style!r}")
        if not 0.5 <= self.camera_height <= 10:
            raise ValueError(f"camera_height must be in [0.5, 10] m, got {self.camera_height}")
        self.gap()  # validates the appearance controls

    def gap(self) -> AppearanceGap:
        return AppearanceGap(self.gap_strength, self.sun_shift, self.color_shift, self.season_shift,
                             self.traffic_change, self.noise_std, self.jpeg_quality)

    def world_cells(self) -> tuple[int, int]:
        """(tile, world) side in cells, both even so the camera sits on a cell corner at the exact centre."""
        t = 2 * int(round(self.tile_m / self.cell_m / 2))
        n = 2 * int(round(t * self.world_margin / 2))
        return t, n

    def as_dict(self) -> dict:
        return asdict(self)


FIELDS = tuple(f.name for f in fields(SynthConfig))

PRESETS = {
    # used by tests: seconds for a handful of samples
    "tiny": dict(aerial_size=64, pano_height=32, pano_width=176, sphere_height=64, sphere_width=128, view_size=48,
                 cell_m=1.0, tile_m=96.0, train=8, val=4),
    # default training runs: cvusa layout at half size, and a small dynamic-scene set
    "small": dict(aerial_size=256, pano_height=112, pano_width=616, sphere_height=256, sphere_width=512,
                  view_size=128, cell_m=0.5625, world_margin=1.3, train=1200, val=300),  # 1 aerial px per cell
    "dynamic_small": dict(view_size=160, cell_m=0.5, world_margin=1.3, train=300, val=100),
    "dynamic_tiny": dict(view_size=48, cell_m=1.0, tile_m=96.0, train=3, val=2),
    # the real datasets' sizes and counts
    "cvusa": dict(train=35532, val=8884),
    "cvact": dict(aerial_size=1200, cell_m=0.2, train=35532, val=8884),
    "dynamic": dict(train=2000, val=500),
}
DEFAULT_PRESET = {"cvusa": "cvusa", "cvact": "cvact", "dynamic": "dynamic"}


def resolve(layout: str, preset: str | None, overrides: dict) -> tuple[SynthConfig, dict]:
    """-> (config, preset sample counts {'train': n, 'val': m})."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; expected one of {LAYOUTS}")
    name = DEFAULT_PRESET[layout] if preset is None else preset
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
    bad = sorted(set(overrides) - set(FIELDS))
    if bad:
        raise TypeError(f"unknown synthetic option(s) {bad}; valid options: {list(FIELDS)}")
    values = {k: v for k, v in PRESETS[name].items() if k not in ("train", "val")}
    values.update({k: v for k, v in overrides.items() if v is not None})
    counts = {k: PRESETS[name][k] for k in ("train", "val")}
    return SynthConfig(**values), counts
