"""The built-in refiner: dense correlation of the query's aligned (IPT, aerial-like) feature map with the tile's,
over every shift and a set of rotations (docs/localisation.md says why this one).

After the inverse polar transform a street panorama looks like an aerial image centred on the camera, north up
when its heading is known. Where the camera stands in the tile is then the shift that best lays the query's map
on the tile's, and an unknown heading is a rotation of the query's map (a circular shift of the panorama). As in
CCVPE (Xia et al., "Convolutional Cross-View Pose Estimation", TPAMI 2023) the answer is a probability over every
position (and heading bin), trained by the likelihood of the truth; the matching here is a plain correlation of
small learnt feature maps, so it trains on a CPU in minutes.

    query S x S -> encoder -> C x n x n (n = S / 2), L2-normalised per position; rotated by each heading bin
    (and drawn `query_scale` times larger where the tile's ground scale differs from the query's);
    its central k x k window (k = kernel_frac * n) slides over the tile's C x n x n map (by FFT):
    score(heading, position) = scale * mean cosine over the window cells that lie on the tile, at the
    (n + 1) x (n + 1) lattice of cell corners (the query's camera sits at its map's centre, a cell corner),
    log-softmax over heading x position.

Near the tile's edge part of the window lies off the tile. `overlap="mean"` (the default) averages over the cells
on the tile, so a camera near the edge is scored on the same footing as one at the centre; `overlap="window"`
divides by the whole window, which scores the edge lower the further the window leaves the tile (the first
refiners were trained so; their checkpoints keep it). `overlap="evidence"` sums the cosines on the tile less a
learnt charge per cell, over the whole window (a log-likelihood ratio of a match when each cell votes with noise):
a position is scored by how much evidence it has. `padding="replicate"` has the encoders repeat the image's border
instead of reading zeros beyond it. Neither is in the recipe (docs/localisation.md measures both).

A tile read with a margin of ground around it (refiner.margin; geoloc/data/tile_context.py stitches it from the
tiles beside it, with a fourth channel saying where imagery lies) gives an m x m reference map, m = n + 2 margin
cells, zero vectors where no imagery lies. The query's window is still laid on the tile's own (n + 1) x (n + 1) cell
corners, and its cells that fall on the margin count like those on the tile wherever they hold imagery: near the
edge the camera's view is matched on the ground beyond it instead of on fewer cells.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from geoloc.models.refiners.refinement import Refinement
from geoloc.registry import register


def _block(c_in: int, c_out: int, stride: int = 1, dilation: int = 1, padding: str = "zeros") -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation, bias=False, padding_mode=padding),
            nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]


def encoder(width: int, channels: int, context: int = 0, padding: str = "zeros") -> nn.Sequential:
    """3 x S x S -> channels x S/2 x S/2, receptive field 29 pixels (one stride-2 stage, then dilated context), and
    32, 64, ... more with each of `context` further blocks of dilation 8, 16, ...; `padding`: what the convolutions
    see beyond the image's border (torch's padding_mode: zeros, or the border's pixels repeated)."""
    def block(c_in, c_out, stride=1, dilation=1):
        return _block(c_in, c_out, stride, dilation, padding)
    more = [layer for k in range(context) for layer in block(2 * width, 2 * width, dilation=8 * 2 ** k)]
    return nn.Sequential(*block(3, width), *block(width, 2 * width, stride=2), *block(2 * width, 2 * width),
                         *block(2 * width, 2 * width, dilation=2), *block(2 * width, 2 * width, dilation=4),
                         *more, nn.Conv2d(2 * width, channels, 1))


OVERLAP = ("mean", "window", "evidence")
PADDING = ("zeros", "replicate")
EVIDENCE_OFFSET = 0.25  # overlap="evidence": the initial charge of each cell on the tile (a mean cosine)


def rotate_maps(maps: torch.Tensor, headings_deg: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
    """B x C x n x n -> B x K x C x n x n: each map turned clockwise (as seen north up) by each heading, about its
    centre, bilinearly, zeros outside; with `scale` ((B,) factors), map b is also drawn scale[b] times larger
    about its centre. A view of heading h shows bearing h at the top of its IPT image; turning it clockwise by h
    puts north back at the top."""
    b, c, h, w = maps.shape
    k = headings_deg.numel()
    theta = torch.deg2rad(headings_deg.to(maps.dtype).to(maps.device))
    cos, sin = torch.cos(theta), torch.sin(theta)
    zero = torch.zeros_like(cos)
    # output point q samples the input at R(-theta) q / scale (affine_grid maps output to input coordinates)
    affine = torch.stack([torch.stack([cos, sin, zero], -1), torch.stack([-sin, cos, zero], -1)], 1)  # K x 2 x 3
    affine = affine[None].expand(b, k, 2, 3)
    if scale is not None:
        shrink = 1.0 / scale.to(maps.dtype).to(maps.device).reshape(b, 1, 1, 1)
        affine = affine * torch.cat([shrink.expand(b, 1, 2, 2), torch.ones_like(shrink).expand(b, 1, 2, 1)], -1)
    grid = F.affine_grid(affine.reshape(b * k, 2, 3), (b * k, c, h, w), align_corners=False)  # BK x n x n x 2
    repeated = maps[:, None].expand(b, k, c, h, w).reshape(b * k, c, h, w)
    out = F.grid_sample(repeated, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.reshape(b, k, c, h, w)


def window_cells(n: int, kernel: int, device=None) -> torch.Tensor:
    """(n + 1) x (n + 1): how many cells of a kernel x kernel window centred on each cell corner of an n x n map
    lie on the map (kernel^2 where the window lies wholly on it)."""
    corner = torch.arange(n + 1, device=device)
    along = (torch.clamp(corner + kernel // 2, max=n) - torch.clamp(corner - kernel // 2, min=0)).float()
    return along[:, None] * along[None, :]


def correlate(query_maps: torch.Tensor, reference_maps: torch.Tensor, headings_deg: torch.Tensor,
              kernel: int, query_scale: torch.Tensor | None = None, overlap: str = "mean",
              offset: torch.Tensor | None = None) -> torch.Tensor:
    """query_maps, reference_maps: B x C x n x n (n even); -> B x K x (n+1) x (n+1) mean dot products of the
    query's central kernel x kernel window (kernel even), rotated by each heading (and drawn query_scale[b] times
    larger), with the reference map, the query's centre laid on each cell corner (i, j) of the reference map: the
    mean over the window's cells on the map (overlap="mean") or over the whole window ("window"), or ("evidence")
    the sum over the window's cells on the map less `offset` for each of them, over the whole window. One query against
    B tiles, given as its map expanded to B (stride 0 along the batch, as an app's top-k refinement passes it), is
    rotated and transformed once instead of B times where the tiles share one scale."""
    b, c, n, _ = query_maps.shape
    m = reference_maps.shape[-1]
    if (reference_maps.shape[:2] != query_maps.shape[:2] or reference_maps.shape[-2] != m or m < n or (m - n) % 2
            or n % 2 or kernel % 2 or not 2 <= kernel <= n):
        raise ValueError(f"correlate takes a B x C x n x n query map (n even), a B x C x m x m reference map with a "
                         f"margin of (m - n) / 2 >= 0 cells and an even kernel <= n; got {tuple(query_maps.shape)}, "
                         f"{tuple(reference_maps.shape)}, kernel {kernel}")
    if overlap not in OVERLAP:
        raise ValueError(f"correlate: overlap must be one of {OVERLAP}, got {overlap!r}")
    if query_scale is not None:
        query_scale = torch.as_tensor(query_scale, dtype=torch.float32).reshape(-1)
        if query_scale.numel() != b or not bool((query_scale > 0).all()) or not bool(query_scale.isfinite().all()):
            raise ValueError(f"correlate: query_scale must hold {b} positive factors, got {query_scale.tolist()}")
    one_scale = query_scale is None or bool((query_scale == query_scale[0]).all())
    shared = b > 1 and query_maps.stride(0) == 0 and one_scale  # the same query map for every tile, at one scale
    windows = turned_windows(query_maps[:1] if shared else query_maps, headings_deg, kernel,
                             None if query_scale is None else query_scale[:1] if shared else query_scale, m)
    return correlate_turned(windows, reference_maps, kernel, overlap, shared, offset, n)


def turned_windows(query_maps: torch.Tensor, headings_deg: torch.Tensor, kernel: int,
                   query_scale: torch.Tensor | None = None, side: int | None = None) -> torch.Tensor:
    """B x C x n x n query maps -> B x K x C x N x (N/2 + 1), N = side + kernel (side: the m x m reference maps'
    side, default n): the spectrum of each map's central kernel x kernel window, turned by each heading (and drawn
    query_scale[b] times larger) and flipped, which correlate_turned lays on m x m reference maps."""
    n = query_maps.shape[-1]
    rotated = rotate_maps(query_maps, headings_deg, query_scale)
    start = (n - kernel) // 2
    window = rotated[..., start:start + kernel, start:start + kernel]  # B x K x C x kernel x kernel
    # a correlation is a convolution with the flipped window: by FFT, several times faster than a grouped conv2d
    # of large kernels on a CPU; padded to m + kernel so nothing wraps around
    size = (n if side is None else side) + kernel
    return torch.fft.rfft2(window.float().flip(-1, -2), s=(size, size))


def context_cells(reference_maps: torch.Tensor, n: int, kernel: int) -> torch.Tensor:
    """B x C x m x m reference maps of an n x n tile with a margin of (m - n) / 2 cells, zero where no imagery
    lies -> B x 1 x (n+1) x (n+1): how many cells with imagery a kernel x kernel window centred on each of the
    tile's cell corners covers (a box sum over an integral image: exact counts)."""
    m = reference_maps.shape[-1]
    valid = (reference_maps.abs().amax(1) > 0).double()  # B x m x m: 1 where a cell holds imagery (5x faster than any)
    integral = F.pad(valid.cumsum(1).cumsum(2), (1, 0, 1, 0))  # B x (m+1) x (m+1)
    corner = torch.arange(n + 1, device=reference_maps.device) + (m - n) // 2
    low, high = (corner - kernel // 2).clamp(0, m), (corner + kernel // 2).clamp(0, m)
    box = (integral[:, high][:, :, high] - integral[:, low][:, :, high] - integral[:, high][:, :, low]
           + integral[:, low][:, :, low])
    return box.float()[:, None]


def correlate_turned(windows: torch.Tensor, reference_maps: torch.Tensor, kernel: int, overlap: str = "mean",
                     shared: bool = False, offset: torch.Tensor | None = None, n: int | None = None) -> torch.Tensor:
    """correlate's scores from its query side already computed: windows, turned_windows of B queries (of n x n
    maps) laid for m x m reference maps, or of one query for every reference map (shared); reference_maps:
    B x C x m x m, the tile's n x n map with a margin of (m - n) / 2 cells of ground around it (n=None: m, no
    margin), its cells zero where no imagery lies -> B x K x (n+1) x (n+1), the tile's cell corners only."""
    m = reference_maps.shape[-1]
    n = m if n is None else n
    size = (m + kernel, m + kernel)
    if windows.shape[-2] != size[0]:
        raise ValueError(f"correlate_turned: the windows were laid for {windows.shape[-2] - kernel} x "
                         f"{windows.shape[-2] - kernel} reference maps, not these {m} x {m} ones "
                         f"(turned_windows' side)")
    reference = torch.fft.rfft2(reference_maps.float(), s=size)  # B x C x M x M/2+1
    product = (torch.einsum("bchw,kchw->bkhw", reference, windows[0]) if shared
               else torch.einsum("bchw,bkchw->bkhw", reference, windows))
    full = torch.fft.irfft2(product, s=size)
    # output corner o: the window's centre on the tile's cell corner o, the reference map's o + margin (full index
    # o + margin + kernel/2 - 1)
    first = kernel // 2 - 1 + (m - n) // 2
    summed = full[..., first:first + n + 1, first:first + n + 1]
    if overlap == "window":
        return summed / (kernel * kernel)
    cells = window_cells(n, kernel, full.device) if m == n else context_cells(reference_maps, n, kernel)
    if overlap == "mean":
        return summed / cells
    if offset is None:
        raise ValueError("correlate: overlap 'evidence' needs the offset each cell on the map is charged")
    return (summed - offset * cells) / (kernel * kernel)


class CorrelationRefiner(nn.Module):
    """Two unshared small encoders (query: the aligned street image, reference: the tile) and a correlation."""

    def __init__(self, channels: int = 16, width: int = 16, kernel_frac: float = 0.5, heading_bins: int = 36,
                 scale: float = 20.0, overlap: str = "mean", context: int = 0, padding: str = "zeros"):
        super().__init__()
        if channels < 1 or width < 1 or heading_bins < 1 or not 0.0 < kernel_frac <= 1.0 or scale <= 0 or context < 0:
            raise ValueError(f"refiner correlation: channels, width, heading_bins must be >= 1, kernel_frac in (0, 1] "
                             f"scale > 0 and context >= 0; got channels={channels}, width={width}, heading_bins="
                             f"{heading_bins}, kernel_frac={kernel_frac}, scale={scale}, context={context}")
        if overlap not in OVERLAP:
            raise ValueError(f"refiner correlation: overlap must be one of {OVERLAP}, got {overlap!r}")
        if padding not in PADDING:
            raise ValueError(f"refiner correlation: padding must be one of {PADDING}, got {padding!r}")
        self.kernel_frac, self.heading_bins, self.overlap = kernel_frac, heading_bins, overlap
        self.query_encoder = encoder(width, channels, context, padding)
        self.reference_encoder = encoder(width, channels, context, padding)
        self.log_scale = nn.Parameter(torch.tensor(math.log(scale)))
        # overlap="evidence": what each cell on the tile is charged (learnt), between a true match's mean cosine
        # and a false one's; only such refiners hold it, so other checkpoints' state dicts are unchanged
        self.evidence_offset = nn.Parameter(torch.tensor(EVIDENCE_OFFSET)) if overlap == "evidence" else None

    def encode_query(self, images: torch.Tensor) -> torch.Tensor:
        """B x 3 x S x S aligned (IPT) street images -> B x C x S/2 x S/2, unit length per position."""
        return F.normalize(self.query_encoder(images), dim=1)

    def encode_reference(self, images: torch.Tensor) -> torch.Tensor:
        """B x 3 x S x S tiles -> B x C x S/2 x S/2, unit length per position; or B x 4 x S' x S' tiles with a
        margin (geoloc/data/tile_context.py: RGB, then 1 where imagery lies) -> B x C x S'/2 x S'/2, zero at each
        cell whose 2 x 2 pixels are not all imagery."""
        if images.shape[1] == 3:
            return F.normalize(self.reference_encoder(images), dim=1)
        rgb, valid = images[:, :3], images[:, 3:]
        cells = -F.max_pool2d(-valid, 2)  # 1 where every pixel of the cell is imagery
        return F.normalize(self.reference_encoder(rgb * valid), dim=1) * (cells > 0.5).to(rgb.dtype)

    def match(self, query_maps: torch.Tensor, reference_maps: torch.Tensor, headings_deg,
              query_scale: torch.Tensor | None = None) -> Refinement:
        headings = torch.as_tensor(headings_deg, dtype=torch.float32, device=query_maps.device).reshape(-1)
        kernel = self.kernel(query_maps.shape[-1])
        return self._refinement(correlate(query_maps, reference_maps, headings, kernel, query_scale, self.overlap,
                                          self.evidence_offset), headings)

    def matcher(self, query_map: torch.Tensor, headings_deg, query_scale: torch.Tensor | None = None):
        """match of one query against tiles that come in parts, its map turned and transformed once for each
        size of reference map: query_map 1 x C x n x n, query_scale one factor for every tile (None: no scale
        input) -> a function of B x C x m x m reference maps (m = n, or with a margin) -> their Refinement, equal to
        match's of the query map expanded to them."""
        headings = torch.as_tensor(headings_deg, dtype=torch.float32, device=query_map.device).reshape(-1)
        n = query_map.shape[-1]
        kernel = self.kernel(n)
        scale = None if query_scale is None else torch.as_tensor(query_scale, dtype=torch.float32).reshape(1)
        laid = {}  # reference side -> the windows' spectra at that size

        def matched(reference_maps: torch.Tensor) -> Refinement:
            m = reference_maps.shape[-1]
            if m not in laid:
                laid[m] = turned_windows(query_map, headings, kernel, scale, m)
            return self._refinement(correlate_turned(laid[m], reference_maps, kernel, self.overlap, True,
                                                     self.evidence_offset, n), headings)
        return matched

    def kernel(self, n: int) -> int:
        """The side of the query's window matched on n x n maps: even, at least 2."""
        return max(2, 2 * round(self.kernel_frac * n / 2))

    def _refinement(self, scores: torch.Tensor, headings: torch.Tensor) -> Refinement:
        scores = scores * self.log_scale.exp()
        b = scores.shape[0]
        return Refinement(F.log_softmax(scores.reshape(b, -1), dim=1).reshape(scores.shape), headings)

    def forward(self, query: torch.Tensor, reference: torch.Tensor, headings_deg,
                query_scale: torch.Tensor | None = None) -> Refinement:
        return self.match(self.encode_query(query), self.encode_reference(reference), headings_deg, query_scale)


@register("refiner", "correlation")
def correlation(channels: int = 16, width: int = 16, kernel_frac: float = 0.5, heading_bins: int = 36,
                scale: float = 20.0, overlap: str = "mean", context: int = 0,
                padding: str = "zeros") -> CorrelationRefiner:
    """channels: matched feature channels; width: the encoders' first width; kernel_frac: the share of the query
    map's side that is matched; heading_bins: candidate headings 360 k / K when the heading is unknown; scale: the
    initial logit scale of a mean cosine (learnt); overlap: mean over the window's cells on the tile, or over the
    whole window, or the evidence (module docstring); context: further dilated blocks that widen the encoders'
    receptive field; padding: what the encoders' convolutions see beyond the image (zeros, or replicate)."""
    return CorrelationRefiner(channels, width, kernel_frac, heading_bins, scale, overlap, context, padding)
