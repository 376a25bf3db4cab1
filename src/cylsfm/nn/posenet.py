"""SfMLearner's pose / explainability network with horizontal wrap-around for cylindrical panoramas."""

from __future__ import annotations

import torch
from torch import nn

from ..errors import check_shape
from ..geometry.compass import compass_yaw
from ..geometry.seam import memory_format_of, pad_cat, relu_pad, roll_columns
from .layers import WrapConv2d, WrapConvTranspose2d, check_input_size, crop_like, init_weights

__all__ = ["PoseExpNet"]

#: The slot prior is stored divided by this gain, so that Adam's steps (about the learning rate in the
#: parameter) move it about as fast as the paper's head finds its forward step (~0.015 in 25 steps).
_PRIOR_GAIN = 10.0


class PoseExpNet(nn.Module):
    """Relative pose and explainability-mask network (SfMLearner), wrap-around aware.

    The target frame and the ``S = n_sources`` source frames are concatenated along channels (target
    first) into a ``3 * (1 + S)``-channel image.  Encoder: 7 stride-2 convs + ReLU with 16, 32, 64,
    128, 256, 256, 256 channels and kernels 7, 5, 3, 3, 3, 3, 3.  Pose head: 1x1 conv to ``6 * S``
    channels, averaged over all positions, scaled by 0.01.  Explainability decoder (optional): from
    the conv5 output, 5 up-convolutions + ReLU (256, 128, 64, 32, 16 channels), each cropped to the
    size of the matching encoder feature (conv4, conv3, conv2, conv1, input), with sigmoid masks
    (3x3 conv to ``S`` channels) at the last four.

    Pose convention: each 6-vector is ``(tx, ty, tz, rx, ry, rz)``, the translation (in the scale of
    the predicted depth) and the axis-angle rotation (radians) of the rigid transform
    ``T_tgt_to_src`` that maps 3-D points in the target camera frame into source camera ``j`` (camera
    axes: x right, y down, z forward).  Conversion to 4x4 matrices is done in :mod:`cylsfm.geometry`.

    Pose heads (``pose_head``):

    * ``"mean"`` (the paper's): the 6-vectors predicted at every position are averaged. With wrap on
      this makes the pose exactly invariant to a common horizontal roll of all frames by a multiple of
      the encoder's stride (128 px), although physically such a roll is a yaw rotation of the camera
      that should rotate the predicted translation and rotation with it.
    * ``"equivariant"``: every column ``j`` of the deepest feature map (azimuth
      ``theta_j = 2 pi j / W_f - pi``, the azimuth of the input column ``128 j`` of a full panorama
      with ``cx = W / 2``) predicts translation and rotation in its own azimuthal frame; each is
      rotated by ``theta_j`` about the vertical axis before the average. Rolling all frames by ``128 m``
      pixels (a yaw of ``Delta = 2 pi 128 m / W``) then rotates the output exactly: ``t -> Q t``,
      ``omega -> Q omega`` with ``Q = yaw_matrix(Delta)``, so random yaw-roll augmentation is possible.
      It is meant for full panoramas.

    With ``compass`` the yaw between the target and each source read in closed form by the visual compass
    (:func:`cylsfm.geometry.compass_yaw`: the circular column shift that aligns the two panoramas) is added
    to the predicted rotation about the vertical axis (``ry``): the network predicts the translation and
    what the compass leaves of the rotation. The compass has no weights and passes no gradient; it needs
    full 360° panoramas (``wrap``).

    With ``antisymmetric`` the network compares two frames at a time: it sees the pair (target, source)
    and the pair (source, target) (6 input channels, one 6-vector each) and predicts their difference,
    ``g(t, s) - g(s, t)``. A prediction from the bias alone is then impossible (a constant cancels), two
    identical frames give exactly zero motion, the pose from b to a is exactly the negated 6-vector of
    the pose from a to b (its inverse to first order), and a source's prediction does not depend on its slot: the network must read the
    motion from the pair. No explainability masks in this mode.

    ``pose_level`` (1-7, default 7) is the encoder level whose features the pose head reads; the deeper
    levels are not built. At 256 px wide level 7 leaves 2 columns and level 5 (stride 32) 8: the
    equivariant head then turns 8 columns' predictions by their own azimuths, each column read from a
    window of 71 px (100 degrees) about it, and is exactly equivariant to rolls by 32 px instead of 128.
    With explainability masks the decoder reads level 5, so ``pose_level`` must be at least 5.

    With ``antipodal`` (full panoramas only) every frame is given to the encoder together with its copy
    turned by half a turn (6 channels a frame), so that the first convolution sees each azimuth and its
    opposite at once: there a yaw moves both the same way and a sideways translation opposite ways,
    which the deepest layers otherwise have to tell apart from features 180 degrees apart.

    With ``slot_prior`` (antisymmetric only) the network also carries a learned 6-vector per source slot,
    ``slot_prior [S, 6]`` (times a gain of 10): the motion by slot that the paper's head learns in its
    bias, here a scaffold that gives the depth network parallax from the first step while the pair
    network learns to read the motion. The pose is the blend ``(1 - w) * pair + w * prior`` with
    ``w = prior_weight`` (an attribute, 0 unless a trainer sets it, faded to 0 during training; in
    ``eval()`` mode always 0); the pair
    network's translation minus the prior's (detached) is kept as ``scaffold_gap [B, S, 3]`` for the
    trainer's distillation term, which teaches the pair network the direction of the motion while the
    prior carries it. With ``prior_weight == 0`` (inference) the prediction is exactly antisymmetric.

    Args:
        n_sources: number of source frames ``S``.
        explainability: whether to build and run the explainability-mask decoder.
        wrap: horizontal wrap-around (requires widths that are multiples of 128).
        pose_head: ``"mean"`` or ``"equivariant"`` (see above).
        compass: add the visual compass's yaw (see above); needs ``wrap``.
        antisymmetric: predict from frame pairs, antisymmetrically (see above).
        slot_prior: carry a learned per-slot motion weighted by ``prior_weight`` (see above).
        pose_level: the encoder level the pose head reads (see above).
        antipodal: frames read with their half-turn copies (see above); needs ``wrap``.
    """

    enc_channels = (16, 32, 64, 128, 256, 256, 256)
    enc_kernels = (7, 5, 3, 3, 3, 3, 3)
    dec_channels = (256, 128, 64, 32, 16)

    def __init__(
        self,
        n_sources: int = 2,
        explainability: bool = True,
        wrap: bool = True,
        pose_head: str = "mean",
        compass: bool = False,
        antisymmetric: bool = False,
        slot_prior: bool = False,
        pose_level: int = 7,
        antipodal: bool = False,
    ) -> None:
        super().__init__()
        if antisymmetric and explainability:
            raise ValueError("antisymmetric pose prediction has no explainability masks")
        if slot_prior and not antisymmetric:
            raise ValueError("slot_prior is a scaffold for the antisymmetric pose network only")
        if not 1 <= pose_level <= len(self.enc_channels):
            raise ValueError(f"pose_level must be in 1..{len(self.enc_channels)}, got {pose_level}")
        if explainability and pose_level < 5:
            raise ValueError("explainability masks read encoder level 5: pose_level must be >= 5")
        if n_sources < 1:
            raise ValueError(f"n_sources must be >= 1, got {n_sources}")
        if antipodal and not wrap:
            raise ValueError("antipodal input needs full 360-degree panoramas (wrap=True)")
        if compass and not wrap:
            raise ValueError("the visual compass needs full 360-degree panoramas (wrap=True)")
        self.compass = compass
        self.antisymmetric = antisymmetric
        if pose_head not in ("mean", "equivariant"):
            raise ValueError(f"pose_head must be 'mean' or 'equivariant', got {pose_head!r}")
        self.pose_head = pose_head
        self.n_sources = n_sources
        self.explainability = explainability
        self.wrap = wrap
        self.pose_level = pose_level
        self.antipodal = antipodal

        per_call = 1 if antisymmetric else n_sources  # sources seen by one pass of the encoder
        channels, kernels = self.enc_channels[:pose_level], self.enc_kernels[:pose_level]
        enc_in = (3 * (2 if antipodal else 1) * (1 + per_call), *channels[:-1])
        self.encoder = nn.ModuleList(
            nn.Sequential(WrapConv2d(cin, cout, k, stride=2, wrap=wrap), nn.ReLU(inplace=True))
            for cin, cout, k in zip(enc_in, channels, kernels, strict=True)
        )
        self.pose_pred = WrapConv2d(channels[-1], 6 * per_call, 1, wrap=wrap)
        self.slot_prior = nn.Parameter(torch.zeros(n_sources, 6)) if slot_prior else None
        self.prior_weight = 0.0
        self.scaffold_gap: torch.Tensor | None = None

        self.upconvs: nn.ModuleList | None = None
        self.mask_heads: nn.ModuleList | None = None
        if explainability:
            up_in = (self.enc_channels[4], *self.dec_channels[:-1])
            self.upconvs = nn.ModuleList(
                nn.Sequential(WrapConvTranspose2d(cin, cout, 3, stride=2, wrap=wrap), nn.ReLU(inplace=True))
                for cin, cout in zip(up_in, self.dec_channels, strict=True)
            )
            # Masks at upconv4, upconv3, upconv2, upconv1 (decoder indices 1..4).
            self.mask_heads = nn.ModuleList(
                WrapConv2d(c, n_sources, 3, wrap=wrap) for c in self.dec_channels[1:]
            )

        init_weights(self)

    #: Validate an input size (:func:`cylsfm.nn.layers.check_input_size`; raises ``InputError``).
    check_input_size = staticmethod(check_input_size)

    def forward(
        self, target: torch.Tensor, sources: torch.Tensor
    ) -> tuple[torch.Tensor, list[torch.Tensor] | None]:
        """Predict target-to-source poses and explainability masks.

        Args:
            target: target frame ``[B, 3, H, W]``, values in ``[0, 1]``.
            sources: source frames ``[B, S, 3, H, W]``, values in ``[0, 1]``.  Both are normalised
                internally as ``(x - 0.5) / 0.5``.  ``H >= 32``; with ``wrap`` ``W`` must be a
                multiple of 128, otherwise ``W >= 32``.

        Returns:
            ``(pose, masks)``: ``pose`` is ``[B, S, 6]`` = ``(tx, ty, tz, rx, ry, rz)`` of ``T_tgt_to_src``
            (translation in depth units, axis-angle rotation in radians) for each source; ``masks`` is a
            list of four per-source explainability masks in ``(0, 1)``, finest first, shaped
            ``[B, S, H_s, W_s]`` for ``s = 0..3`` (``H_0 = H``, ``H_s = ceil(H_{s-1} / 2)``, likewise
            ``W``), or ``None`` when ``explainability`` is False.

        Raises:
            ValueError: for wrongly shaped inputs or an unsupported size.
        """
        check_shape(target, "B,3,H,W", "target")
        check_input_size(target.shape[-1], target.shape[-2], self.wrap)
        b, s = target.shape[0], self.n_sources
        check_shape(sources, ",".join(str(n) for n in (b, s, 3, *target.shape[-2:])), "sources")
        tgt, srcs = (
            (_with_antipodes(target), _with_antipodes(sources)) if self.antipodal else (target, sources)
        )
        if self.antisymmetric:
            first = tgt[:, None].expand_as(srcs).flatten(0, 1)  # [B*S,C,H,W]
            second = srcs.flatten(0, 1)
            pairs, _ = self._predict(
                torch.cat((first, second)), torch.cat((second, first))[:, None], b * s * 2, 1
            )
            pose = (pairs[: b * s] - pairs[b * s :]).view(b, s, 6)
            if self.slot_prior is not None:  # in the graph even at weight 0 (one set of DDP parameters)
                w = self.prior_weight if self.training else 0.0  # never in inference
                prior = _PRIOR_GAIN * self.slot_prior.to(pose.dtype)[None].expand_as(pose)
                self.scaffold_gap = pose[..., :3] - prior[..., :3].detach()
                pose = (1.0 - w) * pose + w * prior
            masks = None
        else:
            pose, masks = self._predict(tgt, srcs, b, s)
        if self.compass:
            pose = pose + _compass_rotation(target, sources).to(pose.dtype)
        return pose, masks

    def _predict(
        self, target: torch.Tensor, sources: torch.Tensor, b: int, s: int
    ) -> tuple[torch.Tensor, list[torch.Tensor] | None]:
        """The encoder, the pose head and the masks on ``[b,3,H,W]`` and ``[b,s,3,H,W]``: ``[b,s,6]``."""
        if self.wrap:
            feats, masks = self._forward_wrapped(target, sources)
        else:
            feats, masks = self._forward_modules(target, sources)

        raw = self.pose_pred(feats[-1])  # [B, 6S, H_f, W_f]
        if self.pose_head == "mean":
            pose = 0.01 * raw.mean(dim=(2, 3)).view(b, s, 6)
        else:
            pose = 0.01 * _rotate_columns_and_average(raw.mean(dim=2).view(b, s, 2, 3, raw.shape[-1]))
        return pose, masks

    def _forward_modules(
        self, target: torch.Tensor, sources: torch.Tensor
    ) -> tuple[list[torch.Tensor], list[torch.Tensor] | None]:
        """Encoder features and masks, layer by layer through the modules."""
        x = torch.cat([target, sources.flatten(1, 2)], dim=1)
        x = (x - 0.5) / 0.5
        feats = []
        for stage in self.encoder:
            x = stage(x)
            feats.append(x)
        if self.upconvs is None or self.mask_heads is None:
            return feats, None
        refs = [feats[3], feats[2], feats[1], feats[0], target]  # conv4, conv3, conv2, conv1, input
        masks: list[torch.Tensor] = []
        x = feats[4]
        for i, upconv in enumerate(self.upconvs):
            x = crop_like(upconv(x), refs[i])
            if i >= 1:
                masks.append(torch.sigmoid(self.mask_heads[i - 1](x)))
        return feats, masks[::-1]

    def _forward_wrapped(
        self, target: torch.Tensor, sources: torch.Tensor
    ) -> tuple[list[torch.Tensor], list[torch.Tensor] | None]:
        """The same with every feature map kept padded for the convolution that reads it (as in DispNet)."""
        first = self.encoder[0][0]
        fmt = memory_format_of(first.weight)
        xp = pad_cat([target, *sources.unbind(1)], first.pad, memory_format=fmt).sub_(0.5).mul_(2.0)
        decoder = self.upconvs is not None and self.mask_heads is not None
        up_pad = max(max(u[0].wrap_left, u[0].wrap_right) for u in self.upconvs) if self.upconvs else 0
        padded: list[tuple[torch.Tensor, int]] = []
        for j, stage in enumerate(self.encoder):
            pad = self.encoder[j + 1][0].pad if j + 1 < len(self.encoder) else self.pose_pred.pad
            if j == 4 and decoder:
                pad = max(pad, up_pad)
            y = stage[0].forward_padded(_narrow(xp, padded[-1][1] - stage[0].pad) if padded else xp)
            xp = relu_pad(y, pad)
            padded.append((xp, pad))
        feats = [_narrow(f, p) for f, p in padded]
        if not decoder:
            return feats, None
        assert self.upconvs is not None and self.mask_heads is not None
        refs = [feats[3], feats[2], feats[1], feats[0], target]
        masks: list[torch.Tensor] = []
        xp, pad = padded[4]
        for i, upconv in enumerate(self.upconvs):
            h, w = refs[i].shape[-2:]
            out, start = upconv[0].forward_padded(xp, pad)
            pad = up_pad if i + 1 < len(self.upconvs) else 0
            if i >= 1:
                pad = max(pad, self.mask_heads[i - 1].pad)
            xp = relu_pad(out, pad, (h, start, w))
            if i >= 1:
                head = self.mask_heads[i - 1]
                masks.append(torch.sigmoid(head.forward_padded(_narrow(xp, pad - head.pad))))
        return feats, masks[::-1]


def _compass_rotation(target: torch.Tensor, sources: torch.Tensor) -> torch.Tensor:
    """``[B,S,6]``: zeros but for ``ry``, the compass's yaw from the target ``[B,3,H,W]`` to each source
    ``[B,S,3,H,W]`` (no gradient)."""
    with torch.no_grad():
        b, s = sources.shape[:2]
        tgt = target[:, None].expand_as(sources).flatten(0, 1)
        yaw = compass_yaw(tgt.float(), sources.flatten(0, 1).float()).view(b, s, 1)
    zeros = torch.zeros_like(yaw)
    return torch.cat((zeros, zeros, zeros, zeros, yaw, zeros), -1)


def _with_antipodes(x: torch.Tensor) -> torch.Tensor:
    """Frames ``[..., 3, H, W]`` with their half-turn copies appended along channels: ``[..., 6, H, W]``."""
    return torch.cat((x, roll_columns(x, x.shape[-1] // 2)), -3)


def _narrow(xp: torch.Tensor, extra: int) -> torch.Tensor:
    """Drop ``extra`` columns on each side of ``xp`` ``[..., W]`` (a view)."""
    return xp[..., extra : xp.shape[-1] - extra] if extra else xp


def _rotate_columns_and_average(cols: torch.Tensor) -> torch.Tensor:
    """``[B,S,2,3,W_f]`` per-column (t, omega) in the columns' own azimuthal frames -> ``[B,S,6]``.

    Column ``j`` sits at azimuth ``theta_j = 2 pi j / W_f - pi``; its vectors are rotated by
    ``yaw_matrix(theta_j)`` (``x' = cos x + sin z``, ``z' = -sin x + cos z``) and averaged over columns.
    """
    w = cols.shape[-1]
    theta = torch.arange(w, device=cols.device, dtype=torch.float32) * (2 * torch.pi / w) - torch.pi
    c, s_ = torch.cos(theta).to(cols.dtype), torch.sin(theta).to(cols.dtype)
    x, y, z = cols[..., 0, :], cols[..., 1, :], cols[..., 2, :]
    rotated = torch.stack((c * x + s_ * z, y, -s_ * x + c * z), -2)  # [B,S,2,3,W_f]
    return rotated.mean(-1).flatten(2)
