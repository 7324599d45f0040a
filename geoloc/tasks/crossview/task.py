"""The cross-view geo-localization task: a Siamese of registered backbones and heads, a registered loss, optimizer
and sampler (geoloc/conf/ groups of the same names).

The paper's method (Li, Tu, Chen, Yu, "Multi-scale attention encoder for street-to-aerial image geo-localization",
CAAI TIT 2023) is backbone=vgg16 head=msae loss=gms_triplet optim=adam: Adam lr 1e-4 (betas 0.9/0.999), StepLR /10
every 80 epochs, 100 epochs, batch 64, alpha 10, MSAE's eq. 3 without an activation; the GMS queue's 1,024 entries
are geoloc's choice (the paper gives no length). Sample4Geo's family is backbone=timm model.shared=true
head=gap loss=infonce optim=adamw with a hard-sample sampler (geoloc/conf/experiment/sample4geo.yaml).
"""

from __future__ import annotations

import warnings

from omegaconf import DictConfig

import geoloc.losses  # noqa: F401  (declares the loss kind and registers its built-ins)
import geoloc.models.optim  # noqa: F401  (the optimizer kind)
from geoloc import registry
from geoloc.config import ConfigError
from geoloc.data import samplers  # noqa: F401  (the sampler kind)
from geoloc.engine import Task
from geoloc.engine import distributed as dist
from geoloc.tasks.crossview.encode import described, encode, plain_pairs_loader
from geoloc.tasks.crossview.transforms import normalised
from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig
from geoloc.models.refiners import check_refiner
from geoloc.tasks.crossview.refine import RefineConfig, refiner_metrics
from geoloc.tasks.crossview.validation import protocol

# What a loss may ask for beyond (query, reference, labels), by declaring it in its `needs` attribute: the batch as
# the data module gives it, each branch's BranchFeatures (models/crossview.py) and the extra query views' B×V×D
# descriptors. They are this rank's, where the descriptors are gathered over ranks.
LOSS_EXTRAS = ("batch", "query_features", "reference_features", "query_views")


def loss_needs(loss) -> tuple[str, ...]:
    """What `loss` declares it needs beyond (query, reference, labels): its `needs` attribute, each a LOSS_EXTRAS
    name, passed as keywords. A loss from before the attribute that names them in its signature gets them too,
    with a DeprecationWarning (read off the signature for one release)."""
    needs = getattr(loss, "needs", None)
    if needs is None:
        named = tuple(registry.accepted(getattr(loss, "forward", loss), dict.fromkeys(LOSS_EXTRAS)))
        if named:
            warnings.warn(f"loss {type(loss).__name__} asks for {list(named)} by naming them in its signature; "
                          f"declare them instead: `needs = {named!r}` (docs/extending.md)", DeprecationWarning,
                          stacklevel=2)
        return named
    unknown = [n for n in needs if n not in LOSS_EXTRAS]
    if isinstance(needs, str) or unknown:
        raise ConfigError(f"loss {type(loss).__name__} declares needs={needs!r}: a tuple of names among "
                          f"{list(LOSS_EXTRAS)}")
    return tuple(needs)


class CrossViewTask(Task):
    monitor = "R@1"
    refine: RefineConfig | None = None  # how the refiner trains and is tested; None: retrieval alone

    def __init__(self, model: CrossViewModelConfig, backbone: DictConfig | dict, head: DictConfig | dict,
                 loss: DictConfig | dict, optim: DictConfig | dict, sampler: DictConfig | dict | None = None,
                 max_epochs: int = 1, refiner: dict | None = None, refine: RefineConfig | None = None):
        super().__init__()
        self.model_cfg, self.optim_section = model, optim
        self.sampler_section = sampler or {"name": "shuffle"}
        self.max_epochs = max_epochs
        self.model = CrossViewModel(backbone, head, model)
        self.loss = registry.build("loss", loss, dim=model.dim)
        if not callable(self.loss):
            raise TypeError(f"loss {loss.get('name')!r} did not build a callable (docs/extending.md)")
        self.loss_extras = loss_needs(self.loss)
        # what is built later fails here, before any data is read: an unknown name or argument
        registry.check("optimizer", optim)
        registry.check("sampler", self.sampler_section)
        self.sampler = None
        self.split = None  # the RetrievalSplit validation scores (validate_on): its relevance and views
        self.protocol = protocol()  # how validation encodes and scores the queries (validate_on)
        self.query_views: dict[str, str] = {}  # {"train": ..., "val": ...}: RetrievalSplit.query_view of each
        # fine-grained localisation inside the tile (refine.py), built last: a run without one builds nothing more
        self.refine = refine if refiner else None
        if self.refine is not None:
            self.refiner = registry.build("refiner", refiner)
            check_refiner(self.refiner, f"refiner {refiner.get('name')!r}")
        else:
            self.refiner = None

    def checkpoint_info(self) -> dict:
        """The query views of the splits trained and validated on ("panorama", "sphere", "image", "aerial"), so
        apps know what the query branch takes (CrossViewEncoder) without guessing from the dataset's name."""
        return {"query_view": dict(self.query_views)}

    # ---- optimisation --------------------------------------------------------------------------------------
    def configure_optimizers(self):
        # the loss's parameters (a learned InfoNCE temperature) train with the network's
        params = list(self.parameters())
        if self.refine is not None and self.refine.stage == "refine":  # the retrieval network stays as loaded
            params = list(self.refiner.parameters())
        opt, sched = registry.build("optimizer", self.optim_section, params=params, max_epochs=self.max_epochs)
        return [opt], [sched] if sched is not None else []

    def train_dataloader(self, dataset, batch_size, engine):
        if getattr(dataset, "views", None) is not None and "query_views" not in self.loss_extras:
            raise ConfigError("the training pairs carry extra query views (views.name is not 'single'), but loss "
                              f"{type(self.loss).__name__} does not take them (`query_views` is not in its `needs`); use "
                              "loss=any_view_infonce or views=single")
        self.query_views["train"] = dataset.split.query_view
        if self.sampler_section.get("name") == "shuffle":  # the engine's own seeded shuffle
            return engine.loader(dataset, batch_size, train=True)
        self.sampler = registry.build("sampler", self.sampler_section, labels=dataset.labels, batch_size=batch_size,
                                      seed=engine.seed, rank=dist.rank(), world_size=dist.world_size(),
                                      neighbours=getattr(dataset, "neighbours", None))
        if getattr(self.sampler, "needs_descriptors", False):
            self._descriptor_loader = plain_pairs_loader(engine, dataset, batch_size)
        return engine.loader(dataset, batch_size, train=True, batch_sampler=self.sampler)

    def on_train_epoch_start(self, engine):
        if hasattr(self.loss, "on_train_epoch_start"):
            self.loss.on_train_epoch_start(engine.epoch)
        if getattr(self.sampler, "needs_descriptors", False) and engine.epoch > 0:
            desc = encode(self, engine, self._descriptor_loader)
            self.sampler.set_descriptors(desc["query"], desc["reference"])

    def on_after_batch_transfer(self, batch):
        """The data module's uint8 images (and their colour jitter draws) → the branches' float input, batched on
        the device (transforms.normalised)."""
        return normalised(batch)

    def training_step(self, batch, engine):
        if self.refine is None:
            return self._retrieval_step(batch)
        scale = {}  # the ground scale as an input (RefineConfig.query_extent_m)
        if self.refine.query_extent_m:
            scale["query_scale"] = self.refine.query_scale(batch["refine_extent_m"].cpu()).to(batch["refine_query"].device)
        out = self.refiner(batch["refine_query"], batch["refine_reference"], self.refine_candidates(), **scale)
        refine_loss = self.refine.loss(out.nll(batch["tile_px"], batch["refine_heading"].float()), batch["tile_px"])
        if self.refine.stage == "refine":
            return {"loss": refine_loss, "refine_loss": refine_loss.detach()}
        retrieval = self._retrieval_step(batch)
        return {**retrieval, "loss": retrieval["loss"] + self.refine.weight * refine_loss,
                "refine_loss": refine_loss.detach()}

    def refine_candidates(self):
        """The heading bins the refiner scores: north alone when the heading is known (RefineConfig.candidates)."""
        return self.refine.candidates(getattr(self.refiner, "heading_bins", 36))

    def train(self, mode: bool = True):
        super().train(mode)
        if mode and self.refine is not None and self.refine.stage == "refine":
            self.model.eval()  # frozen: its batch-norm statistics stay as loaded
        return self

    def _retrieval_step(self, batch):
        extras = {}
        if {"query_features", "reference_features"} & set(self.loss_extras):  # the maps only when asked for
            extras["query_features"], extras["reference_features"] = self.model.features(batch["query"],
                                                                                         batch["reference"])
            query, reference = extras["query_features"].descriptor, extras["reference_features"].descriptor
        else:
            query, reference = self.model(batch["query"], batch["reference"])
        query, reference = query.float(), reference.float()
        if "query_views" in batch:  # extra views of each query (geoloc/tasks/crossview/view_pairs.py): B×V×D
            views = batch["query_views"]
            extras["query_views"] = self.model.query(views.flatten(0, 1)).float().unflatten(0, views.shape[:2])
        # the loss sees the global batch; gradients flow back to every rank's slice
        query_all = dist.all_gather_with_grad(query)
        reference_all = dist.all_gather_with_grad(reference)
        labels_all = dist.all_gather_nograd(batch["label"])
        extras["batch"] = batch
        out = self.loss(query_all, reference_all, labels_all, **{k: extras[k] for k in self.loss_extras})
        return out if isinstance(out, dict) else {"loss": out}

    def on_train_batch_end(self, outputs):
        if hasattr(self.loss, "on_train_batch_end"):
            self.loss.on_train_batch_end()

    # ---- validation ----------------------------------------------------------------------------------------
    def validate_on(self, split, heading_search: bool = False) -> None:
        """The RetrievalSplit validation scores (its relevance, the branch that encodes its queries) and how: each query
        at K candidate headings (heading_search: dataset.random_heading) or at its own (validation.py)."""
        self.split = split
        self.query_views["val"] = split.query_view
        self.protocol = protocol(heading_search)

    def val_dataloaders(self, data, batch_size, engine):
        """One-to-one splits: one loader of pairs. Others: the queries and the gallery apart."""
        if data.pairs is not None:
            return engine.loader(data.pairs, batch_size, train=False)
        return {"query": engine.loader(data.queries, batch_size, train=False),
                "reference": engine.loader(data.references, batch_size, train=False)}

    def validation_step(self, batch, loader: str | None = None):
        """Both sides of a batch of pairs, or the side `loader` names, as encode.described gives them: the queries
        through the protocol's encoder, and the refiner's maps where the task has a refiner."""
        query, reference = self.model.encoders(self.split is not None and self.split.aerial_queries)
        encoders = {"query": self.protocol.query_encoder(query), "reference": reference}
        sides, entry = (encoders, None) if loader is None else ({loader: encoders[loader]}, "image")
        return {**described(self, batch, sides, self.refiner is not None, entry, self.protocol.keep),
                "index": batch["index"]}

    def validation_epoch_end(self, outputs):
        if isinstance(outputs.get("query"), dict):  # queries and references apart: {loader: its outputs}
            outputs = {**outputs["reference"], **outputs["query"]}
        return {**self.protocol.metrics(outputs, self.split), **refiner_metrics(self, self.split, outputs)}
