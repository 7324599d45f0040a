"""Column-wise height-field ray marching ("voxel space" style), vectorised over all columns at once.

Every image column is a vertical half-plane through the camera at one compass azimuth; every pixel of it is a ray
with some elevation (tan_el). Along the column we sample the height field at horizontal distances d_k. A ray hits
sample k when h_k >= z_cam + tan_el * d_k, i.e. when t_k = (h_k - z_cam) / d_k >= tan_el. The first such k is the
first k where the running max M_k = max_{i<=k} t_i reaches tan_el; M is sorted within each column, so one global
np.searchsorted over all columns (each shifted into its own value band) finds every pixel's hit at once.
Nearer samples come first, so occlusion is exact up to the sampling step.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .classes import BUILDINGS
from .light import Lighting
from .world import World, windows_mask

_BAND = 64.0  # |tan| clip; elevations beyond +-89.1 degrees are clipped


@dataclass
class Hits:
    """Per pixel (H x W): albedo in [0,1] (x3), shade factor, class id, horizontal distance (inf: no hit)."""

    albedo: np.ndarray
    shade: np.ndarray
    cls: np.ndarray
    dist: np.ndarray


def sample_distances(cell: float, d_max: float, d_min: float = 0.3) -> np.ndarray:
    """Steps of 0.8 cell near the camera, growing 1.5% per step further out."""
    out = [d_min]
    step0 = 0.8 * cell
    while out[-1] < d_max:
        out.append(out[-1] + max(step0, 0.015 * out[-1]))
    return np.asarray(out)


def march(world: World, light: Lighting, cam_xyz, az_deg: np.ndarray, tan_el: np.ndarray,
          dists: np.ndarray) -> Hits:
    """az_deg (W,), tan_el (H, W) or (H, 1) -> Hits (H x W). Samples must stay inside the world square."""
    cx, cy, cz = (float(v) for v in cam_xyz)
    W, K = len(az_deg), len(dists)
    H = tan_el.shape[0]
    e = np.broadcast_to(np.asarray(tan_el, np.float32), (H, W)).ravel()
    a = np.deg2rad(np.asarray(az_deg, np.float64))
    ux, uy = np.sin(a).astype(np.float32), np.cos(a).astype(np.float32)
    d32 = dists.astype(np.float32)
    # Samples are laid out K x W (sample-major), so the running max runs down contiguous rows.
    idx = _cells(world, cx + d32[:, None] * ux[None], cy + d32[:, None] * uy[None]).ravel()
    hflat = world.height.ravel()
    h = hflat[idx]
    t = np.maximum.accumulate((h.reshape(K, W) - cz) / d32[:, None], axis=0)
    col = np.tile(np.arange(W, dtype=np.int64), H)
    if tan_el.shape[1] == 1 and np.all(np.diff(tan_el[:, 0]) < 0):
        k = _first_hits_shared_rows(t, tan_el[:, 0].astype(np.float32)).ravel()
    else:
        # Integer keys: column in the high bits, tan(elevation) in 1/4096 steps in the low bits.
        band = np.int64(1 << 20)
        keys = (np.clip(t.T, -_BAND, _BAND) * 4096).astype(np.int64) + (np.arange(W, dtype=np.int64) * band)[:, None]
        q = np.ceil(np.clip(e, -_BAND, _BAND) * 4096).astype(np.int64) + col * band
        k = np.searchsorted(keys.ravel(), q) - col * K
    P = H * W
    out_albedo = np.zeros((P, 3), np.float32)
    out_shade = np.zeros(P, np.float32)
    out_cls = np.zeros(P, np.uint8)
    out_dist = np.full(P, np.inf, np.float32)
    hit = np.flatnonzero(k < K)  # the rest see past the world: sky or far haze
    if len(hit):
        albedo, shade, cls, dist = _shade_hits(world, light, (cx, cy, cz), ux, uy, d32, idx, h, k[hit], col[hit],
                                               e[hit])
        out_albedo[hit], out_shade[hit], out_cls[hit], out_dist[hit] = albedo, shade, cls, dist
    return Hits(out_albedo.reshape(H, W, 3), out_shade.reshape(H, W), out_cls.reshape(H, W),
                out_dist.reshape(H, W))


def _first_hits_shared_rows(t: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Panorama case: every column has the same row elevations e (H,), strictly falling down the rows.

    t: the running max M (K, W). Sample k of column j covers the rows at or below c_kj = #{rows with e > M_kj}; c
    falls with k, so the first sample hitting row i is #{k : c_kj > i}: a histogram of c per column and a
    cumulative sum down the rows. -> k (H, W).
    """
    K, W = t.shape
    H = len(e)
    c = np.searchsorted(-e, -t, side="left")  # K*W queries into only H values
    c *= W
    c += np.arange(W)
    hist = np.bincount(c.ravel(), minlength=(H + 1) * W).reshape(H + 1, W)
    return K - np.cumsum(hist[:H], axis=0)


def _shade_hits(world, light, cam, ux, uy, d32, idx, h, k, col, e):
    """Surface, class, albedo and shading at each hit sample k of column col (1-D arrays over hit pixels)."""
    cx, cy, cz = cam
    s = k * len(ux) + col  # samples are K x W
    cell = idx[s]
    h_hit = h[s]
    d_hit = d32[k]
    d_prev = np.where(k > 0, d32[np.maximum(k - 1, 0)], np.float32(0))
    top = (cz + e * d_prev >= h_hit - 1e-3) | (h_hit <= 0.01)
    # Top surfaces: the exact crossing of the ray with the plane z = h_hit, for crisp ground texture.
    e_safe = np.where(e < 0, e, np.float32(-1))
    d_star = np.minimum(np.maximum(np.where(e < 0, (h_hit - cz) / e_safe, d_hit), d_prev), d_hit)
    uxc, uyc = ux[col], uy[col]
    px, py = cx + uxc * d_star, cy + uyc * d_star
    cell2 = _cells(world, px, py)
    exact = top & (np.abs(world.static.height.ravel()[cell2] - h_hit) < 0.3)
    cell = np.where(exact, cell2, cell)
    dist = np.where(top, d_star, d_hit)

    cls = world.cls.ravel()[cell]
    albedo = np.empty((len(k), 3), np.float32)
    ex = np.flatnonzero(exact)
    albedo[ex] = _bilinear(world.static.top, world, px[ex], py[ex])
    rest = np.flatnonzero(~exact)
    cr = cell[rest]  # np.take gathers whole rows much faster than fancy indexing
    src = np.where(top[rest, None], np.take(world.top.reshape(-1, 3), cr, axis=0),
                   np.take(world.wall.reshape(-1, 3), cr, axis=0))
    albedo[rest] = src * np.float32(1 / 255)
    shade = np.empty(len(k), np.float32)
    tp = np.flatnonzero(top)
    shade[tp] = light.top_shade(cell[tp])

    wall = np.flatnonzero(~top)
    if len(wall):
        nx, ny = light.wall_normal(cell[wall])
        flat = (nx == 0) & (ny == 0)
        nx = np.where(flat, -uxc[wall], nx)  # no gradient at this cell: face the camera
        ny = np.where(flat, -uyc[wall], ny)
        sv = light.sun.vector()
        z = np.clip(cz + e[wall] * d_hit[wall], 0, h_hit[wall])
        occl = 0.7 + 0.3 * np.clip(z / 3.0, 0, 1)
        shade[wall] = occl * (light.sun.ambient + light.sun.direct * 0.9 * np.maximum(nx * sv[0] + ny * sv[1], 0))
        bld = cls[wall] == BUILDINGS
        if bld.any():
            wb = wall[bld]
            along = px[wb] * -ny[bld] + py[wb] * nx[bld]
            win = wb[windows_mask(z[bld], along)]
            albedo[win] = albedo[win] * 0.35 + np.array([0.12, 0.16, 0.22], np.float32)
    return albedo, shade, cls, dist


def _cells(world: World, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Flat cell index of metre coordinates, clamped to the grid."""
    half, inv, n = world.extent / 2, 1.0 / world.cell, world.n
    # Clamping before truncation gives the same cells as after it (truncation is monotone and 0, n-1 are whole).
    col = (x + half) * inv
    row = (half - y) * inv
    np.clip(col, 0, n - 1, out=col)
    np.clip(row, 0, n - 1, out=row)
    row = row.astype(np.int32 if n * n < 2**31 else np.int64)
    row *= n
    row += col.astype(row.dtype)
    return row


def _bilinear(img: np.ndarray, world: World, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup of an N x N x 3 uint8 cell image at metre coordinates -> (n, 3) float in [0, 1].

    One cv2.remap call; remap maps are limited to 32767 columns, so the points are laid out in rows of 4096."""
    n = len(x)
    if n == 0:  # cv2.remap refuses an empty map (a view that sees only walls, e.g. from inside a building)
        return np.zeros((0, 3), np.float32)
    rows = -(-n // 4096)
    half, inv = world.extent / 2, 1.0 / world.cell
    mx = np.zeros(rows * 4096, np.float32)
    my = np.zeros(rows * 4096, np.float32)
    mx[:n] = (x + half) * inv - 0.5  # cv2 puts integer coordinates at cell centres
    my[:n] = (half - y) * inv - 0.5
    out = cv2.remap(img, mx.reshape(rows, 4096), my.reshape(rows, 4096), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:n].astype(np.float32) * np.float32(1 / 255)
