"""Neural networks: wrap-around layers, SfMLearner's DispNet and the pose networks (from parts) for cylindrical panoramas."""

from cylsfm.nn.dispnet import DispNet
from cylsfm.nn.layers import WrapConv2d, WrapConvTranspose2d, crop_like, set_wrap, wrap_upsample2x
from cylsfm.nn.posenet import PairPoseNet, PoseExpNet, PoseModel, VisualCompass

__all__ = [
    "DispNet",
    "PairPoseNet",
    "PoseExpNet",
    "PoseModel",
    "VisualCompass",
    "WrapConv2d",
    "WrapConvTranspose2d",
    "crop_like",
    "set_wrap",
    "wrap_upsample2x",
]
