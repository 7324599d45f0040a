"""What a refiner answers: a joint log-probability over heading bins and positions in the tile, and the estimates
read from it.

Positions are a lattice over the whole tile that includes its edges: point (i, j) of an R x C map lies at the tile
fraction (i / (R - 1), j / (C - 1)) (row down, column right), so (0.5, 0.5) is the tile centre and (0, 0) its
top-left corner, whatever the tile's pixel size. Headings are bearings in degrees clockwise from north of the
query's centre column (geoloc/tasks/crossview/views.py).

A refiner is an nn.Module with three methods (docs/extending.md "A refiner"):
    encode_query(B x 3 x S x S aligned query images)   -> query maps (any tensor a refiner matches)
    encode_reference(B x 3 x S x S tile images)        -> reference maps
    match(query maps, reference maps, headings (K,) degrees)  -> Refinement (one per query-tile pair)
so an app encodes a gallery's tiles once and matches each query against its top-k tiles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class Refinement:
    """log_prob: B x K x R x C, log-probabilities summing to 1 over (heading bin, row, column) per pair;
    headings_deg: (K,) the bearing of each bin (degrees, clockwise from north)."""

    log_prob: torch.Tensor
    headings_deg: torch.Tensor

    def __post_init__(self):
        if self.log_prob.ndim != 4 or self.log_prob.shape[1] != self.headings_deg.numel():
            raise ValueError(f"a Refinement holds B x K x R x C log-probabilities for K headings; got "
                             f"{tuple(self.log_prob.shape)} for {self.headings_deg.numel()} headings")
        if min(self.log_prob.shape[2:]) < 2:
            raise ValueError(f"a refinement map needs at least 2 x 2 positions, got {tuple(self.log_prob.shape[2:])}")

    @property
    def position_log_prob(self) -> torch.Tensor:
        """B x R x C: log P(position), heading marginalised."""
        return torch.logsumexp(self.log_prob, dim=1)

    def position(self, smoothing: float = 0.0) -> torch.Tensor:
        """B x 2 (row, col) tile fractions of the most probable position, refined between lattice points by a
        parabola through the log-probabilities of its neighbours on each axis. With `smoothing` > 0 the
        probability is first blurred by a Gaussian whose sigma is that share of the tile's side: the answer is then
        the point with the most probability around it, which a narrow spurious peak beside a broad true one does
        not win (docs/localisation.md measures it)."""
        logp = self.position_log_prob
        if smoothing > 0:
            logp = _blurred(logp.exp(), smoothing).clamp_min(torch.finfo(logp.dtype).tiny).log()
        b, rows, cols = logp.shape
        best = logp.flatten(1).argmax(1)
        r, c = best // cols, best % cols
        batch = torch.arange(b, device=logp.device)
        dr = _parabola_peak(logp, batch, r, c, rows, axis=0)
        dc = _parabola_peak(logp, batch, r, c, cols, axis=1)
        return torch.stack([(r + dr) / (rows - 1), (c + dc) / (cols - 1)], 1).clamp(0.0, 1.0)

    def heading(self) -> torch.Tensor:
        """(B,) degrees in [0, 360): the most probable heading bin, with the position marginalised, refined by a
        parabola through its neighbouring bins when the bins are evenly spaced around the circle."""
        logp = torch.logsumexp(self.log_prob.flatten(2), dim=2)  # B x K
        k = logp.shape[1]
        best = logp.argmax(1)
        heading = self.headings_deg.to(logp.device)[best].float()
        if k >= 3 and _evenly_around(self.headings_deg):
            b = torch.arange(logp.shape[0], device=logp.device)
            left, mid, right = logp[b, (best - 1) % k], logp[b, best], logp[b, (best + 1) % k]
            heading = heading + _vertex(left, mid, right) * 360.0 / k
        return heading % 360.0

    def mass_within(self, radius: torch.Tensor | float, extent: torch.Tensor, smoothing: float = 0.0,
                    at: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) the probability mass of the positions within `radius` metres of the estimate (position(smoothing),
        or `at` where the caller has read it already): the refiner's own score of its answer (what a calibrator
        maps to P(error <= radius)). extent: B x 2 (height, width) metres the tile covers."""
        prob = self.position_log_prob.exp()
        b, rows, cols = prob.shape
        extent = torch.as_tensor(extent, dtype=prob.dtype, device=prob.device).reshape(b, 2)
        at = (self.position(smoothing) if at is None else at) * torch.tensor([rows - 1, cols - 1], device=prob.device)
        ys = torch.arange(rows, device=prob.device, dtype=prob.dtype)[None, :, None]
        xs = torch.arange(cols, device=prob.device, dtype=prob.dtype)[None, None, :]
        dy = (ys - at[:, 0, None, None]) * (extent[:, 0, None, None] / (rows - 1))
        dx = (xs - at[:, 1, None, None]) * (extent[:, 1, None, None] / (cols - 1))
        inside = (dy ** 2 + dx ** 2) <= torch.as_tensor(radius, dtype=prob.dtype) ** 2
        return (prob * inside).flatten(1).sum(1).clamp(0.0, 1.0)

    def nll(self, position: torch.Tensor, heading_deg: torch.Tensor | None = None) -> torch.Tensor:
        """(B,) -log P(truth): the true position (B x 2 tile fractions) spread bilinearly over its four lattice
        neighbours, and the true heading ((B,) degrees, None for one bin) linearly over its two nearest bins of an
        even circle of bins: a cross-entropy with a soft target, so sub-lattice truth is learnt."""
        target = _position_target(position, *self.log_prob.shape[2:])  # B x R x C
        k = self.log_prob.shape[1]
        if k == 1 or heading_deg is None:
            return -(target * self.position_log_prob).flatten(1).sum(1)
        bins = _heading_target(heading_deg, self.headings_deg.to(position.device))  # B x K
        return -(bins[:, :, None, None] * target[:, None] * self.log_prob).flatten(1).sum(1)


def check_refiner(refiner, where: str) -> None:
    """A clear error when a registered refiner lacks the methods the task calls."""
    missing = [m for m in ("encode_query", "encode_reference", "match") if not callable(getattr(refiner, m, None))]
    if missing or not isinstance(refiner, torch.nn.Module):
        raise TypeError(f"{where} built {type(refiner).__name__}, which is not a refiner: an nn.Module with "
                        f"encode_query, encode_reference and match (missing {missing}; docs/extending.md)")


def _vertex(left, mid, right):
    """The offset in [-0.5, 0.5] of a parabola's vertex through (-1, left), (0, mid), (1, right)."""
    denom = left - 2 * mid + right
    offset = 0.5 * (left - right) / torch.where(denom.abs() > 1e-12, denom, torch.full_like(denom, -1e-12))
    return torch.nan_to_num(offset, nan=0.0).clamp(-0.5, 0.5)


def _blurred(prob: torch.Tensor, smoothing: float) -> torch.Tensor:
    """B x R x C probabilities convolved with a Gaussian of sigma `smoothing` x (R - 1) rows and x (C - 1) columns
    (separable, truncated at 3 sigma); what lies beyond the map counts as zero, so a point near the edge sums only
    the mass on the tile."""
    out = prob[:, None]
    for axis, size in ((2, prob.shape[1]), (3, prob.shape[2])):
        sigma = smoothing * (size - 1)
        radius = int(math.ceil(3 * sigma))
        x = torch.arange(-radius, radius + 1, dtype=prob.dtype, device=prob.device)
        kernel = torch.exp(-0.5 * (x / sigma) ** 2)
        kernel = (kernel / kernel.sum()).reshape((1, 1, -1, 1) if axis == 2 else (1, 1, 1, -1))
        out = F.conv2d(out, kernel, padding=(radius, 0) if axis == 2 else (0, radius))
    return out[:, 0]


def _parabola_peak(logp, batch, r, c, size, axis: int):
    """The sub-lattice offset of the peak at (r, c) along `axis` (0 at an edge of the map)."""
    i = r if axis == 0 else c
    inner = (i > 0) & (i < size - 1)
    lo, hi = (i - 1).clamp(min=0), (i + 1).clamp(max=size - 1)
    if axis == 0:
        left, mid, right = logp[batch, lo, c], logp[batch, r, c], logp[batch, hi, c]
    else:
        left, mid, right = logp[batch, r, lo], logp[batch, r, c], logp[batch, r, hi]
    return torch.where(inner, _vertex(left, mid, right), torch.zeros_like(mid))


def _evenly_around(headings: torch.Tensor) -> bool:
    k = headings.numel()
    steps = torch.diff(torch.cat([headings.double(), headings[:1].double() + 360.0]))
    return bool(torch.allclose(steps, torch.full_like(steps, 360.0 / k), atol=1e-6))


def _position_target(position: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    """B x R x C bilinear weights of each (row, col) fraction on the lattice."""
    b = position.shape[0]
    y = position[:, 0].clamp(0, 1) * (rows - 1)
    x = position[:, 1].clamp(0, 1) * (cols - 1)
    y0, x0 = y.floor().clamp(max=rows - 2), x.floor().clamp(max=cols - 2)
    fy, fx = y - y0, x - x0
    target = position.new_zeros(b, rows, cols)
    batch = torch.arange(b, device=position.device)
    y0, x0 = y0.long(), x0.long()
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            target[batch, y0 + dy, x0 + dx] += wy * wx
    return target


def _heading_target(heading_deg: torch.Tensor, headings: torch.Tensor) -> torch.Tensor:
    """B x K linear weights of each heading on its two nearest bins (bins evenly around the circle, or a sorted
    arc of bins: then the weight goes to the nearest bin)."""
    k = headings.numel()
    heading_deg = heading_deg.to(headings.dtype)
    if _evenly_around(headings):
        pos = ((heading_deg - headings[0]) % 360.0) / (360.0 / k)
        lo = pos.floor()
        frac = pos - lo
        out = heading_deg.new_zeros(heading_deg.shape[0], k)
        batch = torch.arange(heading_deg.shape[0], device=heading_deg.device)
        out[batch, lo.long() % k] += 1 - frac
        out[batch, (lo.long() + 1) % k] += frac
        return out
    diff = (heading_deg[:, None] - headings[None, :] + 180.0) % 360.0 - 180.0
    return F.one_hot(diff.abs().argmin(1), k).to(heading_deg.dtype)
