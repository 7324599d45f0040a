"""The renderer's exact output: sha256 of a few rendered images of each layout at its tiny preset (seed 3, one train
and one val sample), taken as the arrays handed to the codec (their shape, dtype, format and quality with their
pixels), and of the text files beside them. They were recorded with the renderer before it was made faster; a
speed-up must leave them as they are, since the default run's figures rest on the same images. Digests of the
arrays, not of the files, so that a new OpenCV build's JPEG / PNG encoder does not fail the test
(benchmarks/check_synthetic_bytes.py compares whole files with another checkout's on the same machine).
"""
import hashlib

import numpy as np
import pytest
import geoloc.synthetic.layouts as LY
from geoloc.synthetic import generate

PRESETS = {"cvusa": "tiny", "cvact": "tiny", "dynamic": "dynamic_tiny", "vigor": "vigor_tiny", "u1652": "u1652_tiny"}
DIGESTS = {
    "cvact": {
        "ANU_data_small/streetview/synthetic_000000000002_grdView.jpg":
            "a54135d04f0bbbb2827a6d72f26143a1d0804d824b5b0e51f67d436479e7a59d",
        "ANU_data_small/satview_polish/synthetic_000000000002_satView_polish.jpg":
            "c1128872b607a73310c8e40d03d8a4444b0b2957f552a00f2a07eb1fb08754d8",
    },
    "cvusa": {
        "bingmap/19/0000002.jpg": "c1128872b607a73310c8e40d03d8a4444b0b2957f552a00f2a07eb1fb08754d8",
        "streetview/panos/0000002.jpg": "9504bee46803b15281b96eb20f97762012e990e54ec6e928d88383d6680d5189",
        "streetview/annotations/0000002.png": "0108b2627ae0e2099463dc6deef5f1cf4e93c9e5c954b72f05509c48d7ae28d8",
        "splits/val-19zl.csv": "b5f39791bc7189fe72aee188ac8a2fe0413186db7dbb508c2a0b18654918d126",
        "positions.csv": "7e9be4aa75ab9e93e6d9ba7ababe53e338cca6dd59de563f65dd58b210d706c8",
    },
    "dynamic": {
        "rgb_dynamic/0000003.png": "74f1ba988a71af5d300947677c983a6b042142046800df99ba0f4479f10ee230",
        "rgb_static/0000003.png": "9ae5a3fab8bd13d370acdf3fd6df773beb7c3c8b06b405a649895d28301d2dd1",
        "label_dynamic/0000003.png": "7ae853d020099464b5b44db752d6f6cdbfe7a15cc227c6899df4b4d9f2224255",
        "mask_dynamic/0000003.png": "57e1afbbb25a4c8cbd1c19ae1cc02ef1eae600e7d881e78b1f8609409654df47",
        "splits/val.csv": "38bda3e71ae7d2a078e46fbd1f92ffca2eac8f3844cb6c40b850fc1d7ab598ab",
    },
    "u1652": {
        "test/gallery_drone/0003/image-02.jpeg": "fa0dd0c8aba75f556139c344b7fb092867250d7905c43b221f7f2fa371342016",
        "test/gallery_satellite/0003/0003.jpg": "5cc85ba94ffe7870783ff736ebc52a12038b92134d8f1033a499e9d6b8d7ecbf",
        "train/drone/0001/image-03.jpeg": "d54c81de31154844b0d678819d6fbf0225c051bd29917fb03951bb99a2b9ed1c",
    },
    "vigor": {
        "NewYork/panorama/YeKcaHg5gBmpk_Rfo4wS2R,40.757578,-73.985133,.jpg":
            "da11320a4af509e1f0f23d7a89955532965b7f1c38259a896c2c2223f69f9ba9",
        "NewYork/satellite/satellite_40.758_-73.9855.png":
            "caee53e00b9c9b4ef1a7f163eab2e0ad1dc96700a4723d4a7862f4f686b6c66f",
        "splits/NewYork/pano_label_balanced.txt": "0c7ced544dd8635b1cea8cae6bb4dfb6b6dd131c234e41944a25e138ed57702d",
    },
}


def array_digest(img: np.ndarray, ext: str, quality: int = 95) -> bytes:
    """What the test writes in place of an encoded image: the sha256 of the array and how it would be encoded."""
    header = repr((img.shape, str(img.dtype), ext, int(quality))).encode()
    return hashlib.sha256(header + np.ascontiguousarray(img).tobytes()).hexdigest().encode()


@pytest.mark.parametrize("layout", sorted(DIGESTS))
def test_rendered_images_are_unchanged(layout, tmp_path, monkeypatch):
    monkeypatch.setattr(LY, "encode", array_digest)
    root = generate(layout, tmp_path / layout, 1, 1, seed=3, preset=PRESETS[layout], progress=False)
    found = {name: hashlib.sha256((root / name).read_bytes()).hexdigest() for name in DIGESTS[layout]}
    assert found == DIGESTS[layout]
