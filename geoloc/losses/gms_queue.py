"""Global hard-negative queue (GMS) of the multi-scale attention encoder paper (Li et al., CAAI TIT 2023).

A fixed-length FIFO of reference (aerial) descriptors: after each step's loss, the hardest in-batch negative of
every query is pushed, detached; the next steps use the queue as extra negatives for the query -> reference
direction of ``soft_margin_triplet``, masking entries of the query's own location. As in MoCo (He et al., CVPR
2020) the queue lives in registered buffers, so checkpoints restore it, and it is gathered over ranks before
each push, so every rank holds the same queue.
"""
from __future__ import annotations

import torch
from torch import nn

from geoloc.engine.distributed import all_gather_variable

__all__ = ["GMSQueue"]


class GMSQueue(nn.Module):
    """FIFO of ``size`` reference descriptors of dimension ``dim``; ``size = 0`` disables it ("w/o GMS").

    Buffers: ``descriptors`` (size x dim), ``ids`` (size,) long location ids with -1 for an empty slot, and
    ``ptr`` (0-d long), the next slot to write.
    """

    def __init__(self, size: int, dim: int, dtype: torch.dtype = torch.float32):
        super().__init__()
        if size < 0 or dim <= 0:
            raise ValueError(f"GMSQueue needs size >= 0 and dim > 0, got size={size}, dim={dim}")
        self.size, self.dim = int(size), int(dim)
        self.register_buffer("descriptors", torch.zeros(self.size, self.dim, dtype=dtype))
        self.register_buffer("ids", torch.full((self.size,), -1, dtype=torch.long))
        self.register_buffer("ptr", torch.zeros((), dtype=torch.long))

    @property
    def enabled(self) -> bool:
        return self.size > 0

    def __len__(self) -> int:
        """Number of filled slots."""
        return int((self.ids >= 0).sum())

    def negatives(self, query_ids: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Extra negatives for the B queries with location ids ``query_ids`` (B,).

        Returns (size x dim descriptors, B x size bool keep-mask): empty slots and entries of the query's own
        location are masked out. Returns (None, None) when the queue is disabled, which
        ``soft_margin_triplet(..., extra_negatives=None, extra_mask=None)`` reads as "no queue".
        """
        if not self.enabled:
            return None, None
        query_ids = query_ids.to(self.ids.device).long().reshape(-1)
        mask = (self.ids[None, :] >= 0) & (self.ids[None, :] != query_ids[:, None])
        return self.descriptors, mask

    @staticmethod
    @torch.no_grad()
    def hardest_negatives(query: torch.Tensor, reference: torch.Tensor,
                          ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For each query (B x D), the closest reference (B x D) of another location: the diagonal and every
        reference with the query's id are excluded. Returns (B x D detached descriptors, B ids), row i for query
        i; a query without any valid negative (e.g. B = 1) gets a zero row and id -1, which ``push`` skips."""
        ids = ids.to(query.device).long().reshape(-1)
        sim = query.detach().float() @ reference.detach().float().t()  # closest = largest a.b = smallest 2-2a.b
        invalid = (ids[:, None] == ids[None, :]) | torch.eye(len(ids), dtype=torch.bool, device=sim.device)
        best = sim.masked_fill(invalid, float("-inf")).argmax(dim=1)
        has_negative = ~invalid.all(dim=1)
        desc = torch.where(has_negative[:, None], reference.detach()[best], torch.zeros_like(reference))
        return desc, torch.where(has_negative, ids[best], torch.full_like(ids, -1))

    @torch.no_grad()
    def push(self, descriptors: torch.Tensor, ids: torch.Tensor) -> None:
        """Enqueue N descriptors (N x dim) with their location ids (N,), oldest entries first out; entries with
        id -1 are skipped.

        Under torch.distributed the entries of all ranks are gathered first (rank order), so every rank writes
        the same entries. When more than ``size`` entries arrive at once, only the last ``size`` are kept.
        """
        if not self.enabled:
            return
        if descriptors.ndim != 2 or descriptors.shape[1] != self.dim or ids.shape != descriptors.shape[:1]:
            raise ValueError(f"push needs N x {self.dim} descriptors and N ids, got {tuple(descriptors.shape)} "
                             f"and {tuple(ids.shape)}")
        descriptors = descriptors.detach().to(self.descriptors)
        ids = ids.detach().to(self.ids)
        descriptors, ids = all_gather_variable(descriptors), all_gather_variable(ids)  # ranks may differ in N
        keep = ids >= 0  # id -1: a query that had no negative to give
        descriptors, ids = descriptors[keep], ids[keep]
        n = ids.shape[0]
        if n == 0:
            return
        # Same slots as pushing the entries one by one: entry k goes to (ptr + k) % size, the last one wins.
        kept = min(n, self.size)
        slots = (int(self.ptr) + n - kept + torch.arange(kept, device=self.ids.device)) % self.size
        self.descriptors[slots] = descriptors[n - kept:]
        self.ids[slots] = ids[n - kept:]
        self.ptr.fill_((int(self.ptr) + n) % self.size)

    def extra_repr(self) -> str:
        return f"size={self.size}, dim={self.dim}"

