"""Neural networks: wrap-around layers, SfMLearner's DispNet and PoseExpNet for cylindrical panoramas."""

from cylsfm.nn.dispnet import DispNet
from cylsfm.nn.layers import WrapConv2d, WrapConvTranspose2d, crop_like, set_wrap, wrap_upsample2x
from cylsfm.nn.posenet import PoseExpNet

__all__ = [
    "DispNet",
    "PoseExpNet",
    "WrapConv2d",
    "WrapConvTranspose2d",
    "crop_like",
    "set_wrap",
    "wrap_upsample2x",
]
