"""A sampler plug-in: the training pairs in file order, in batches (a rank takes every world_size-th batch)."""

from geoloc.registry import register


class InOrder:
    needs_descriptors = False

    def __init__(self, n: int, batch_size: int, rank: int, world_size: int):
        batches = [list(range(i, i + batch_size)) for i in range(0, n - batch_size + 1, batch_size)]
        self.batches, self.epoch = batches[rank::world_size], 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self):
        return iter([[(i, self.epoch) for i in batch] for batch in self.batches])

    def __len__(self) -> int:
        return len(self.batches)


@register("sampler", "in_order")
def in_order(labels, batch_size: int, rank: int, world_size: int) -> InOrder:
    return InOrder(len(labels), batch_size, rank, world_size)
