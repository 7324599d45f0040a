"""Label ids: the MMDIP paper's 8 static classes plus the 2 dynamic ones, and a palette to draw them."""
import numpy as np

NONE, BUILDINGS, FENCES, OTHERS, ROADLINES, ROAD, SIDEWALK, VEGETATION = range(8)
VEHICLE, PEDESTRIAN = 8, 9

STATIC_CLASSES = ("None", "Buildings", "Fences", "Others", "Roadlines", "Road", "Sidewalk", "Vegetation")
ALL_CLASSES = STATIC_CLASSES + ("Vehicle", "Pedestrian")

# CARLA-like colours, used for figures only.
PALETTE = np.array(
    [
        (0, 0, 0),
        (70, 70, 70),
        (190, 153, 153),
        (220, 220, 0),
        (157, 234, 50),
        (128, 64, 128),
        (244, 35, 232),
        (107, 142, 35),
        (0, 0, 142),
        (220, 20, 60),
    ],
    np.uint8,
)


def colorize(labels: np.ndarray) -> np.ndarray:
    """H x W class ids -> H x W x 3 RGB."""
    return PALETTE[np.clip(labels, 0, len(PALETTE) - 1)]
