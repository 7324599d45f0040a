"""Networks: the cross-view Siamese (VGG16 + MSAE) and the dynamic-scene models (ERFNet, U-Net, PatchGAN, FCN)."""

from geoloc.models.crossview import CrossViewModel, CrossViewModelConfig
from geoloc.models.erfnet import ERFNet
from geoloc.models.fcn import FCN8s
from geoloc.models.patchgan import PatchGAN
from geoloc.models.unet import UNet

__all__ = ["CrossViewModel", "CrossViewModelConfig", "ERFNet", "FCN8s", "PatchGAN", "UNet"]
