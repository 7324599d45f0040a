"""Generator settings and named presets.

A preset is a bundle of sizes for all layouts plus default sample counts; keyword overrides replace single
fields. `SynthConfig` rejects unknown fields and bad values at construction, before any work starts. The vigor and
u1652 layouts have a few settings of their own (`VigorOptions`, `U1652Options`); they live apart from
`SynthConfig` so the markers of the older layouts' datasets (which record the whole config) stay as they were.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from .appearance import AppearanceGap
from .styles import STYLES

LAYOUTS = ("cvusa", "cvact", "dynamic", "vigor", "u1652")


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
    view_nuisance: float | None = None  # strength in (0, 1] of the nuisances drawn apart per view (nuisance.py)

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
        if self.view_nuisance is not None and not 0 < self.view_nuisance <= 1:
            raise ValueError(f"view_nuisance is a strength in (0, 1] (or null: none), got {self.view_nuisance}")

    def gap(self) -> AppearanceGap:
        return AppearanceGap(self.gap_strength, self.sun_shift, self.color_shift, self.season_shift,
                             self.traffic_change, self.noise_std, self.jpeg_quality)

    def world_cells(self) -> tuple[int, int]:
        """(tile, world) side in cells, both even so the camera sits on a cell corner at the exact centre."""
        t = 2 * int(round(self.tile_m / self.cell_m / 2))
        n = 2 * int(round(t * self.world_margin / 2))
        return t, n

    def as_dict(self) -> dict:
        """The marker's config. view_nuisance appears only when set, so the markers of datasets rendered before it
        existed (which it leaves pixel for pixel as they were) still match."""
        out = asdict(self)
        if out["view_nuisance"] is None:
            del out["view_nuisance"]
        return out


@dataclass(frozen=True)
class VigorOptions:
    """vigor layout: the first `cities` of VIGOR's cities (Chicago, NewYork, SanFrancisco, Seattle), each a
    `grid` x `grid` array of satellite tiles whose centres lie half a tile apart."""

    cities: int = 4
    grid: int = 16

    def __post_init__(self):
        _count(self, "cities", 1, 4)
        _count(self, "grid", 2, 200)


@dataclass(frozen=True)
class U1652Options:
    """u1652 layout: `drone_views` oblique views per building on an orbit around it; `extra_gallery` buildings
    only in the test galleries (University-1652 has 250 such distractors)."""

    drone_views: int = 54
    extra_gallery: int = 0

    def __post_init__(self):
        _count(self, "drone_views", 1, 99)  # two-digit image-NN names, as in the release
        _count(self, "extra_gallery", 0, 9999)


def _count(obj, name: str, low: int, high: int) -> None:
    v = getattr(obj, name)
    try:
        ok = not isinstance(v, bool) and float(v) == int(v) and low <= v <= high
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {v!r}")
    object.__setattr__(obj, name, int(v))


FIELDS = tuple(f.name for f in fields(SynthConfig))
OPTIONS = {"vigor": VigorOptions, "u1652": U1652Options}
OPTION_FIELDS = {layout: tuple(f.name for f in fields(cls)) for layout, cls in OPTIONS.items()}

PRESETS = {
    # used by tests: seconds for a handful of samples
    "tiny": dict(aerial_size=64, pano_height=32, pano_width=176, sphere_height=64, sphere_width=128, view_size=48,
                 cell_m=1.0, tile_m=96.0, train=8, val=4),
    # default training runs: cvusa layout at half size, and a small dynamic-scene set
    "small": dict(aerial_size=256, pano_height=112, pano_width=616, sphere_height=256, sphere_width=512,
                  view_size=128, cell_m=0.5625, world_margin=1.3, train=1200, val=300),  # 1 aerial px per cell
    "dynamic_small": dict(view_size=160, cell_m=0.5, world_margin=1.3, train=300, val=100),
    "dynamic_tiny": dict(view_size=48, cell_m=1.0, tile_m=96.0, train=3, val=2),
    # vigor: train / val count panoramas per city; u1652: buildings
    "vigor_tiny": dict(aerial_size=64, sphere_height=64, sphere_width=128, cell_m=1.0, tile_m=96.0,
                       world_margin=1.5, cities=2, grid=3, train=4, val=3),
    "vigor_small": dict(aerial_size=256, sphere_height=256, sphere_width=512, cell_m=0.38, tile_m=72.96,
                        world_margin=2.0, cities=4, grid=8, train=64, val=32),
    # vigor_small's world and training panoramas with 512 test panoramas a city (2,048; vigor_small's 128 are its
    # first): the calibration's ECE needs >= 2,000 test queries (docs/confidence.md)
    "vigor_small_2k": dict(aerial_size=256, sphere_height=256, sphere_width=512, cell_m=0.38, tile_m=72.96,
                           world_margin=2.0, cities=4, grid=8, train=64, val=512),
    # vigor_small with tiles at each real VIGOR city's ground extent (640 px times CCVPE's metres per pixel):
    # Seattle 64.52 m, Chicago 71.21, New York 72.48, San Francisco 75.61, against vigor_small's 72.96. The world
    # cell is set so that a tile is a whole number of cells (a multiple of 4) within 1% of vigor_small's 0.38 m
    **{f"vigor_small_{city}_scale": dict(aerial_size=256, sphere_height=256, sphere_width=512, tile_m=extent,
                                         cell_m=extent / cells, world_margin=2.0, cities=4, grid=8, train=64, val=32)
       for city, extent, cells in (("seattle", 64.52, 168), ("chicago", 71.21, 188), ("newyork", 72.48, 192),
                                   ("sanfrancisco", 75.61, 200))},
    # the CPU recipes' larger worlds (geoloc/conf/experiment/vigor_cpu.yaml, u1652_cpu.yaml): the small presets' image
    # sizes and test sets, six / eight times the training places (the small ones over-fit within a few epochs)
    "vigor_medium": dict(aerial_size=256, sphere_height=256, sphere_width=512, cell_m=0.38, tile_m=72.96,
                         world_margin=2.0, cities=4, grid=8, train=384, val=32),
    # vigor_medium's world and training panoramas with 512 test panoramas a city (vigor_medium's 128 are its first):
    # the refiner's whole-tile calibration, fitted on vigor_medium's held-out training panoramas, scored on >= 2,000
    "vigor_medium_2k": dict(aerial_size=256, sphere_height=256, sphere_width=512, cell_m=0.38, tile_m=72.96,
                            world_margin=2.0, cities=4, grid=8, train=384, val=512),
    # VIGOR cross-area's larger training world (docs/datasets.md): vigor_medium's tile and image sizes, each city 16 x 16
    # tiles (4x the tiles and 3.0x the area of vigor_medium's 8 x 8) with 768 training panoramas (3 per tile)
    "vigor_large": dict(aerial_size=256, sphere_height=256, sphere_width=512, cell_m=0.38, tile_m=72.96,
                        world_margin=2.0, cities=4, grid=16, train=768, val=32),
    "u1652_tiny": dict(aerial_size=64, view_size=48, cell_m=1.0, tile_m=96.0, world_margin=2.0, fov_deg=60.0,
                       drone_views=3, extra_gallery=1, train=3, val=2),
    "u1652_small": dict(aerial_size=256, view_size=192, cell_m=0.5, tile_m=120.0, world_margin=2.0, fov_deg=60.0,
                        drone_views=8, extra_gallery=16, train=48, val=48),
    "u1652_medium": dict(aerial_size=256, view_size=192, cell_m=0.5, tile_m=120.0, world_margin=2.0, fov_deg=60.0,
                         drone_views=8, extra_gallery=16, train=384, val=48),
    # the real datasets' sizes and counts (vigor and u1652: image sizes; the real counts would be days of CPU)
    "cvusa": dict(train=35532, val=8884),
    "cvact": dict(aerial_size=1200, cell_m=0.2, train=35532, val=8884),
    "dynamic": dict(train=2000, val=500),
    "vigor": dict(aerial_size=640, sphere_height=1024, sphere_width=2048, cell_m=0.228, tile_m=72.96,
                  world_margin=2.0, cities=4, grid=16, train=500, val=500),
    "u1652": dict(aerial_size=512, view_size=512, cell_m=0.25, tile_m=120.0, world_margin=2.0, fov_deg=60.0,
                  drone_views=54, extra_gallery=250, train=701, val=701),
}
DEFAULT_PRESET = {layout: layout for layout in LAYOUTS}


def resolve(layout: str, preset: str | None, overrides: dict) -> tuple[SynthConfig, dict]:
    """-> (config, preset sample counts {'train': n, 'val': m}). Overrides may also name the layout's options."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; expected one of {LAYOUTS}")
    name = DEFAULT_PRESET[layout] if preset is None else preset
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
    mine = OPTION_FIELDS.get(layout, ())
    bad = sorted(set(overrides) - set(FIELDS) - set(mine))
    foreign = {k: lay for lay, names in OPTION_FIELDS.items() for k in names if k in bad}
    if foreign:
        k = sorted(foreign)[0]
        raise TypeError(f"synthetic option {k!r} belongs to layout {foreign[k]!r}, not {layout!r}")
    if bad:
        raise TypeError(f"unknown synthetic option(s) {bad}; valid options: {list(FIELDS) + list(mine)}")
    values = {k: v for k, v in PRESETS[name].items() if k in FIELDS}
    values.update({k: v for k, v in overrides.items() if v is not None and k in FIELDS})
    counts = {k: PRESETS[name][k] for k in ("train", "val")}
    return SynthConfig(**values), counts


def resolve_options(layout: str, preset: str | None, overrides: dict):
    """The layout's own options (VigorOptions / U1652Options) from the preset and overrides; None for the
    layouts without any. Call after resolve(), which checks the names."""
    if layout not in OPTIONS:
        return None
    name = DEFAULT_PRESET[layout] if preset is None else preset
    keys = OPTION_FIELDS[layout]
    values = {k: v for k, v in PRESETS[name].items() if k in keys}
    values.update({k: v for k, v in overrides.items() if v is not None and k in keys})
    return OPTIONS[layout](**values)
