"""The renderer's exact bytes: sha256 of a few files of each layout at its tiny preset (seed 3, one train and one val
sample), recorded before the renderer was made faster. A speed-up must leave them as they are: the default run's
figures rest on the same images. The JPEG / PNG bytes also depend on the OpenCV build's codecs; should an OpenCV
upgrade alone change them, check every layout with benchmarks/check_synthetic_bytes.py against the old code first.
"""
import hashlib

import pytest
from geoloc.synthetic import generate

PRESETS = {"cvusa": "tiny", "cvact": "tiny", "dynamic": "dynamic_tiny", "vigor": "vigor_tiny", "u1652": "u1652_tiny"}
DIGESTS = {
    "cvusa": {
        "bingmap/19/0000002.jpg": "9159aa4e045ce4192d1dcd0d072cbd758f28810c4341b8208047610b7c1230bd",
        "streetview/panos/0000002.jpg": "2619c80014561f02b207f32443579be4dff0df71c9ed9808eed6756bfbc519fb",
        "streetview/annotations/0000002.png": "582d38ac2e437f46b63f8cbfe9052934bd7ecca83250c8343027c1c6a3c1fd0d",
        "splits/val-19zl.csv": "b5f39791bc7189fe72aee188ac8a2fe0413186db7dbb508c2a0b18654918d126",
        "positions.csv": "7e9be4aa75ab9e93e6d9ba7ababe53e338cca6dd59de563f65dd58b210d706c8",
    },
    "cvact": {
        "ANU_data_small/streetview/synthetic_000000000002_grdView.jpg":
            "4e7f8cf2022ec3babe1be98e32432e6a83223561bde045a0024a2424297aa3bf",
        "ACT_data.mat": "82922f52b53ef462e33d21cb1850c1b82b842ff99f7f863ed6c9c2d5ae91bc89",
    },
    "dynamic": {
        "rgb_dynamic/0000003.png": "f9a00e2ce64a198d230eb0921dbc1810fee156161fc2caa0ede89d09ef2a86b5",
        "rgb_static/0000003.png": "1294413f54cdb59ea9dadf90076bbc3b0d5015c8b933fa9c3226e64100aeb7db",
        "label_dynamic/0000003.png": "fffec43f54d537ce74bff2d0e1159b491772bbd64492f05d6fa2a92770073814",
        "mask_dynamic/0000003.png": "d91272c71b0016453493398031991cfd7e4d8933d6345074d56eb103426622ad",
        "splits/val.csv": "38bda3e71ae7d2a078e46fbd1f92ffca2eac8f3844cb6c40b850fc1d7ab598ab",
    },
    "vigor": {
        "NewYork/panorama/YeKcaHg5gBmpk_Rfo4wS2R,40.757578,-73.985133,.jpg":
            "93ba2244bdac5e4395d43340d873ff7ab7bb5d6554561f2c4995d0aba0dc61a8",
        "NewYork/satellite/satellite_40.758_-73.9855.png":
            "f92cad681a79d82b75b1d92e06f813bd353e08e72428b950701a9ef060cd2bf8",
        "splits/NewYork/pano_label_balanced.txt": "0c7ced544dd8635b1cea8cae6bb4dfb6b6dd131c234e41944a25e138ed57702d",
    },
    "u1652": {
        "test/gallery_drone/0003/image-02.jpeg": "f13ab86f6573fd2076ae461067fe7434a887992d029643da6ded5082ec6de597",
        "test/gallery_satellite/0003/0003.jpg": "2b4cf088a756a1012d92be93ba9f70acaa2a064dcfc3d1364c0c4d2c286c62af",
        "train/drone/0001/image-03.jpeg": "d6b6c8eba33a3994895bd090f774237d1e09f1edd2119f78edba61966eea0085",
    },
}


@pytest.mark.parametrize("layout", sorted(DIGESTS))
def test_rendered_bytes_are_unchanged(layout, tmp_path):
    root = generate(layout, tmp_path / layout, 1, 1, seed=3, preset=PRESETS[layout], progress=False)
    found = {name: hashlib.sha256((root / name).read_bytes()).hexdigest() for name in DIGESTS[layout]}
    assert found == DIGESTS[layout]
