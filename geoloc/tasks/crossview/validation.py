"""How cross-view validation encodes and scores its queries, chosen with the split (CrossViewTask.validate_on):
`Retrieval`, one descriptor per query, or `HeadingSearch`, each at K candidate headings (heading.py). Each side is
encoded by encode.described, as in the gallery; the refiner's metrics come on top (refine.refiner_metrics)."""

from __future__ import annotations

from functools import partial

from geoloc.data.relevance import Relevance
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.eval.average_precision import AP_KEYS
from geoloc.eval.descriptors import check_descriptors
from geoloc.eval.geo_error import METRE_KEYS
from geoloc.eval.keys import KeySet, guarded
from geoloc.eval.recall import HIT_RATE_KEYS, recall_keys
from geoloc.eval.retrieval_metrics import metric_plan, scored_metrics, split_metrics, split_plan
from geoloc.tasks.crossview.heading import candidate_descriptors, heading_metrics, heading_plan

KS = (1, 5, 10)  # the R@K validation reports


class Retrieval:
    """Each query one descriptor (B×D), ranked against the split's relevance (split_metrics); descriptors without
    their split: query i against reference i. plan(None): every key set some split could give (hit rate with
    semi-positives, AP with labels, metres with positions)."""

    keep: tuple[str, ...] = ()  # what the metrics take of a batch of queries beyond its images

    def query_encoder(self, encoder):
        return encoder

    def plan(self, split: RetrievalSplit | None) -> list[KeySet]:
        return [recall_keys(KS), HIT_RATE_KEYS, AP_KEYS, METRE_KEYS] if split is None else split_plan(split, KS)

    def metrics(self, outputs: dict, split: RetrievalSplit | None) -> dict:
        # Non-finite descriptors raise; a collapse (ties count in the query's favour, so one shared descriptor would
        # score R@1 = 100%) reports every metric at its worst. The same checks guard the saved-gallery path.
        query, reference = outputs["query"], outputs["reference"]
        spread = check_descriptors(query, reference)
        if split is None:
            relevance = Relevance.one_to_one(query.shape[0], reference.shape[0])
            return guarded(lambda: scored_metrics(query, reference, relevance), spread,
                           metric_plan(relevance, KS, located=False))
        return guarded(lambda: split_metrics(query, reference, split), spread, self.plan(split))


class HeadingSearch:
    """Each query of unknown heading encoded at K candidate headings (B×K×D), ranked by its best one, and the
    heading read off its true pair (heading.heading_metrics)."""

    keep = ("heading",)  # each query's true heading, degrees

    def query_encoder(self, encoder):
        return partial(candidate_descriptors, encoder)

    def plan(self, split: RetrievalSplit | None) -> list[KeySet]:
        return heading_plan(KS)

    def metrics(self, outputs: dict, split: RetrievalSplit | None) -> dict:
        query, reference = outputs["query"], outputs["reference"]
        spread = check_descriptors(query.flatten(0, 1), reference)
        relevance = None if split is None else split.relevance
        return guarded(lambda: heading_metrics(query, reference, outputs["heading"], relevance=relevance), spread,
                       self.plan(split))


def protocol(heading_search: bool = False) -> Retrieval | HeadingSearch:
    """The protocol of a split validated at each query's known heading, or searched (dataset.random_heading)."""
    return HeadingSearch() if heading_search else Retrieval()
