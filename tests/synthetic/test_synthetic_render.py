"""Synthetic renders against their own ground truth: orientation, perspective labels, dynamic vs static."""
import numpy as np
import pytest
from geoloc.synthetic.classes import ROAD, ROADLINES, SIDEWALK
from geoloc.synthetic.world_config import resolve
from geoloc.synthetic.panorama import panorama_column_bearing, panorama_rays
from geoloc.synthetic.samples import (
    make_place,
    render_pair,
    render_place_views,
    sample_rngs,
)

polar = pytest.importorskip("geoloc.data.polar")

PAIR = dict(aerial_size=128, pano_height=64, pano_width=256, cell_m=0.5, tile_m=96.0)
VIEW = dict(view_size=64, cell_m=0.5, tile_m=96.0, style="urban", traffic=3.0)


def _zscore(p):
    return (p - p.mean()) / (p.std() + 1e-9)


def _best_shift(aerial_labels, pano_labels, width):
    """Circular shift (columns) that best aligns per-class column profiles of the SAFA polar transform of the
    aerial label map with those of the panorama's labels. Several classes, because a straight road alone is
    symmetric under a half turn."""
    total = np.zeros(width)
    for classes in ((ROAD, ROADLINES), (1,), (7,), (SIDEWALK,), (0,)):
        m = np.isin(aerial_labels, classes).astype(np.uint8) * 255
        pol = polar.aerial_to_polar(np.dstack([m, m, m]), (pano_labels.shape[0], width))[..., 0] > 127
        ground = pano_labels if classes == (1,) else pano_labels[int(0.6 * pano_labels.shape[0]) :]
        a, b = pol.mean(0), np.isin(ground, classes).mean(0)
        if a.std() > 1e-6 and b.std() > 1e-6:
            total += [np.mean(_zscore(a) * np.roll(_zscore(b), k)) for k in range(width)]
    k = int(np.argmax(total))
    return k if k < width // 2 else k - width


def test_panorama_bearings():
    az, tan_el = panorama_rays(64, 256, 0.58)
    assert az[0] == 180.0 and az[128] == 0.0 and az[64] == 270.0  # south, north (centre), west
    assert panorama_column_bearing(192, 256) == 90.0
    assert np.all(np.diff(tan_el[:, 0]) < 0)  # elevation falls down the rows
    assert tan_el[int(0.58 * 64) - 1, 0] > 0 > tan_el[int(0.58 * 64), 0]


def test_polar_of_aerial_lines_up_with_panorama():
    cfg, _ = resolve("cvusa", "tiny", PAIR)
    shifts = []
    for i in range(6):
        out = render_pair(cfg, 0, "train", i, sphere=False)
        shifts.append(_best_shift(out["aerial_labels"], out["pano_labels"], 256))
    assert max(abs(s) for s in shifts) <= 4, shifts  # 4 of 256 columns = 5.6 degrees


def test_full_sphere_lines_up_too():
    cfg, _ = resolve("cvact", "tiny", dict(PAIR, sphere_height=128, sphere_width=256))
    out = render_pair(cfg, 0, "val", 1, sphere=True)
    band = out["pano_labels"][32:96]  # SAFA's CVACT crop: the middle half
    assert abs(_best_shift(out["aerial_labels"], band, 256)) <= 4


def _ground_points(pose, size, fov, cam_h, vs, us):
    """Brute force: where the pinhole ray through pixel (v, u) meets the ground plane, in world metres."""
    f = (size / 2) / np.tan(np.deg2rad(fov) / 2)
    xs, ys = [], []
    for v, u in zip(vs, us):
        d_cam = np.array([u + 0.5 - size / 2, f, -(v + 0.5 - size / 2)])  # right, forward, up
        t = cam_h / -d_cam[2]
        yaw = np.deg2rad(pose.yaw)
        fwd, right = np.array([np.sin(yaw), np.cos(yaw)]), np.array([np.cos(yaw), -np.sin(yaw)])
        p = np.array([pose.x, pose.y]) + t * (d_cam[1] * fwd + d_cam[0] * right)
        xs.append(p[0])
        ys.append(p[1])
    return np.array(xs), np.array(ys)


@pytest.fixture(scope="module")
def views():
    cfg, _ = resolve("dynamic", "dynamic_tiny", VIEW)
    for i in range(8):  # the first place whose reference view sees traffic
        v = render_place_views(cfg, 0, "train", i)
        if (v[0]["mask_dynamic"] > 0).sum() > 20:
            return cfg, i, v
    pytest.fail("no traffic in 8 urban places")


def test_perspective_labels_agree_with_world(views):
    cfg, index, v = views
    place = make_place(cfg, sample_rngs(0, "train", index)[0])
    ref = v[0]
    lab = ref["label_static"]
    vs, us = np.nonzero(np.isin(lab, (ROAD, ROADLINES, SIDEWALK)))
    assert len(vs) > 100
    x, y = _ground_points(ref["pose"], cfg.view_size, cfg.fov_deg, cfg.camera_height, vs, us)
    idx, inside = place.world.cell_index(x, y)
    agree = place.world.cls.ravel()[idx][inside] == lab[vs, us][inside]
    assert inside.mean() > 0.99 and agree.mean() > 0.97


def test_dynamic_and_static_differ_only_at_agents_and_their_shadows(views):
    _, _, v = views
    for view in v:
        mask = view["mask_dynamic"] > 0
        st, dy = view["rgb_static"].astype(int), view["rgb_dynamic"].astype(int)
        outside = ~mask
        assert np.array_equal(view["label_static"][outside], view["label_dynamic"][outside])
        diff = np.abs(st - dy).max(-1)
        changed = outside & (diff > 0)
        # outside the mask only cast shadows may change a pixel: darker, never brighter
        assert np.all(dy[changed] <= st[changed])
        assert changed.mean() < 0.1
        assert view["label_static"].max() <= 7
    # the query is another pose, time and traffic
    assert v[0]["pose"] != v[1]["pose"] and v[0]["conditions"].sun != v[1]["conditions"].sun


def test_two_processes_rendering_one_cache_share_it(tmp_path):
    """Two runs on an empty cache (a seed sweep on a shared one): one renders under the lock, the other waits and
    reuses the folder; neither fails on the other's temp files, and the files are those of one render."""
    import subprocess
    import sys

    from geoloc.synthetic import generate

    root = tmp_path / "cache" / "cvusa"
    code = ("import sys; from geoloc.synthetic import generate; "
            "generate('cvusa', sys.argv[1], 6, 3, seed=3, preset='tiny', progress=False)")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(root)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert sum("waiting for another process" in out for out, _ in outs) <= 1
    alone = generate("cvusa", tmp_path / "alone", 6, 3, seed=3, preset="tiny", progress=False)
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(alone) for p in alone.rglob("*") if p.is_file())
    assert not [f for f in files if f.name.endswith(".tmp")]
    assert all((root / f).read_bytes() == (alone / f).read_bytes() for f in files)


def test_a_render_waits_for_the_process_that_holds_the_folder(tmp_path):
    import subprocess
    import sys

    from geoloc.synthetic.generate import rendering

    root = tmp_path / "cvusa"
    code = ("import sys; from geoloc.synthetic import generate; "
            "generate('cvusa', sys.argv[1], 2, 1, preset='tiny', progress=False); print('rendered')")
    with rendering(root):
        proc = subprocess.Popen([sys.executable, "-u", "-c", code, str(root)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().startswith(f"waiting for another process that is rendering {root}")
        assert proc.poll() is None and not root.exists()  # it waits, and writes nothing meanwhile
    assert proc.stdout.readline().strip() == "rendered" and proc.wait(timeout=600) == 0
