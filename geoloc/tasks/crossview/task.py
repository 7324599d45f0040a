"""The cross-view geo-localization task: a Siamese of registered backbones and heads, a registered loss, optimizer
and sampler (conf/ groups of the same names).

The paper's method (Li, Tu, Chen, Yu, "Multi-scale attention encoder for street-to-aerial image geo-localization",
CAAI TIT 2023) is backbone=vgg16 head=msae loss=gms_triplet optim=adam: Adam lr 1e-4 (betas 0.9/0.999), StepLR /10
every 80 epochs, 100 epochs, batch 64, alpha 10, queue 1,024. Sample4Geo's family is backbone=timm model.shared=true
head=gap loss=infonce optim=adamw with a hard-sample sampler (conf/experiment/sample4geo.yaml).
"""

from __future__ import annotations

import torch
from omegaconf import DictConfig

import geoloc.losses  # noqa: F401  (declares the loss kind and registers its built-ins)
from geoloc import registry
from geoloc.data import samplers  # noqa: F401  (the sampler kind)
from geoloc.engine import Task
from geoloc.engine import distributed as dist
from geoloc.eval import recall_at_k
from geoloc.eval.descriptors import check_descriptors, guarded_recall
from geoloc.tasks.crossview.heading import collapsed_heading_metrics, heading_metrics
from geoloc.eval.retrieval_metrics import collapsed_split_metrics, split_metrics
from geoloc.models import optim  # noqa: F401  (the optimizer kind)
from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig


class CrossViewTask(Task):
    monitor = "R@1"

    def __init__(self, model: CrossViewModelConfig, backbone: DictConfig | dict, head: DictConfig | dict,
                 loss: DictConfig | dict, optim: DictConfig | dict, sampler: DictConfig | dict | None = None,
                 max_epochs: int = 1):
        super().__init__()
        self.model_cfg, self.optim_section = model, optim
        self.sampler_section = sampler or {"name": "shuffle"}
        self.max_epochs = max_epochs
        self.model = CrossViewModel(backbone, head, model)
        self.loss = registry.build("loss", loss, dim=model.dim)
        if not callable(self.loss):
            raise TypeError(f"loss {loss.get('name')!r} did not build a callable (docs/extending.md)")
        # what is built later fails here, before any data is read: an unknown name or argument
        registry.check("optimizer", optim, runtime=("params", "max_epochs"))
        registry.check("sampler", self.sampler_section,
                       runtime=("labels", "batch_size", "seed", "rank", "world_size", "neighbours"))
        self.sampler = None
        self.split = None  # the validation RetrievalSplit, for metrics beyond one-to-one

    # ---- optimisation --------------------------------------------------------------------------------------
    def configure_optimizers(self):
        # the loss's parameters (a learned InfoNCE temperature) train with the network's
        opt, sched = registry.build("optimizer", self.optim_section, params=list(self.parameters()),
                                    max_epochs=self.max_epochs)
        return [opt], [sched] if sched is not None else []

    def train_dataloader(self, dataset, batch_size, engine):
        if self.sampler_section.get("name") == "shuffle":  # the engine's own seeded shuffle
            return engine.loader(dataset, batch_size, train=True)
        self.sampler = registry.build("sampler", self.sampler_section, labels=dataset.labels, batch_size=batch_size,
                                      seed=engine.seed, rank=dist.rank(), world_size=dist.world_size(),
                                      neighbours=getattr(dataset, "neighbours", None))
        if getattr(self.sampler, "needs_descriptors", False):
            from geoloc.tasks.crossview.encode import plain_pairs_loader

            self._descriptor_loader = plain_pairs_loader(engine, dataset, batch_size)
        return engine.loader(dataset, batch_size, train=True, batch_sampler=self.sampler)

    def on_train_epoch_start(self, engine):
        if hasattr(self.loss, "on_train_epoch_start"):
            self.loss.on_train_epoch_start(engine.epoch)
        if getattr(self.sampler, "needs_descriptors", False) and engine.epoch > 0:
            from geoloc.tasks.crossview.encode import encode

            desc = encode(self, engine, self._descriptor_loader)
            self.sampler.set_descriptors(desc["query"], desc["reference"])

    def training_step(self, batch, engine):
        query, reference = self.model(batch["query"], batch["reference"])
        query, reference = query.float(), reference.float()
        # the loss sees the global batch; gradients flow back to every rank's slice
        query_all = dist.all_gather_with_grad(query)
        reference_all = dist.all_gather_with_grad(reference)
        labels_all = dist.all_gather_nograd(batch["label"])
        out = self.loss(query_all, reference_all, labels_all)
        return out if isinstance(out, dict) else {"loss": out}

    def on_train_batch_end(self, outputs):
        if hasattr(self.loss, "on_train_batch_end"):
            self.loss.on_train_batch_end()

    # ---- validation ----------------------------------------------------------------------------------------
    def val_dataloaders(self, data, batch_size, engine):
        """One-to-one splits: one loader of pairs. Others: the queries and the gallery apart."""
        self.split = data.split
        if data.pairs is not None:
            return engine.loader(data.pairs, batch_size, train=False)
        return {"query": engine.loader(data.queries, batch_size, train=False),
                "reference": engine.loader(data.references, batch_size, train=False)}

    def validation_step(self, batch, loader: str | None = None):
        if loader is None and "heading" in batch:  # unknown heading: B×K×3×H×W candidate inputs per query
            candidates = batch["query"]
            # B images at a time, as without the search: K·B at once would hold K times the activations
            flat = candidates.flatten(0, 1)
            query = torch.cat([self.model.query(part) for part in flat.split(candidates.shape[0])])
            query = query.unflatten(0, candidates.shape[:2])
            return {"query": query, "reference": self.model.reference(batch["reference"]), "index": batch["index"],
                    "heading": batch["heading"]}
        if loader is None:
            query, reference = self.model(batch["query"], batch["reference"])
            return {"query": query, "reference": reference, "index": batch["index"]}
        query_encoder, reference_encoder = self.model.encoders(self.split is not None and self.split.aerial_queries)
        encoder = query_encoder if loader == "query" else reference_encoder
        return {"descriptor": encoder(batch["image"]), "index": batch["index"]}

    def validation_epoch_end(self, outputs):
        if "query" in outputs and isinstance(outputs["query"], dict):  # two loaders
            query, reference = outputs["query"]["descriptor"], outputs["reference"]["descriptor"]
        else:
            query, reference = outputs["query"], outputs["reference"]
        # Non-finite descriptors raise; a collapse (ties count in the query's favour, so one shared descriptor would
        # score R@1 = 100%) reports recall 0. The same checks guard the saved-gallery path (gallery.py).
        if query.ndim == 3:  # Q×K×D: each query at K candidate headings (geoloc/tasks/crossview/heading.py)
            spread = check_descriptors(query.flatten(0, 1), reference)
            return guarded_recall(lambda: heading_metrics(query, reference, outputs["heading"]), spread,
                                  collapsed=collapsed_heading_metrics())
        spread = check_descriptors(query, reference)
        if self.split is None or self.split.one_to_one:
            return guarded_recall(lambda: recall_at_k(query, reference), spread)
        return guarded_recall(lambda: split_metrics(query, reference, self.split), spread,
                              collapsed=collapsed_split_metrics(self.split))
