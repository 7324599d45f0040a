"""Networks: the cross-view Siamese (VGG16 + MSAE) and the dynamic-scene models (ERFNet, U-Net, PatchGAN, FCN)."""

from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig
from geoloc.models.erfnet import ERFNet

__all__ = ["CrossViewModel", "CrossViewModelConfig", "ERFNet"]
