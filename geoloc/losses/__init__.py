"""Losses: the cross-view soft-margin triplet and its GMS queue, symmetric InfoNCE (Sample4Geo), and the
dynamic-scene segmentation / GAN losses. This package declares the `loss` kind (the cross-view training loss,
config section `loss`) and registers its built-ins: gms_triplet (gms_triplet_loss.py) and infonce."""
from geoloc import registry
from geoloc.losses import any_view, gms_triplet_loss  # noqa: F401  (register any_view_infonce, gms_triplet)
from geoloc.losses.gan import lsgan_d_loss, lsgan_g_loss
from geoloc.losses.gms_queue import GMSQueue
from geoloc.losses.infonce import InfoNCELoss, info_nce
from geoloc.losses.perceptual import VGGPerceptualLoss
from geoloc.losses.segmentation import class_weights
from geoloc.losses.triplet import soft_margin_triplet

registry.declare("loss", section="loss", runtime=("dim",))

__all__ = ["GMSQueue", "InfoNCELoss", "VGGPerceptualLoss", "class_weights", "info_nce", "lsgan_d_loss", "lsgan_g_loss",
           "soft_margin_triplet"]
