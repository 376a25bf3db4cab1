"""Where the pose network's snippet ATE comes from: its steps with one part replaced by the truth.

    python experiments/snippet_decomposition.py experiments/out/default-120

On the benchmark's test rides (experiments/out/data, split test) the network's consecutive steps are
chained and scored (snippet ATE, 5 frames, as `cylsfm evaluate pose`), then again with, for every step,
the true length (rescaled to the network's median step), the true translation direction (or only its
azimuth or elevation), the true rotation, or both direction and rotation; with every step's length set to the ride's median (constant length); with
the steps' translations smoothed over time (Gaussian, sigma in steps; rotations kept); and with
translations fused with the network's own two-frame steps (least squares over the ride, weight w).
Figures are means over the snippets and ratios to constant velocity.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from cylsfm.data.format import scan_dataset
from cylsfm.data.splits import read_split, split_path
from cylsfm.evaluate.pose_metrics import chain_poses, invert, snippet_ates
from cylsfm.evaluate.pose_source import predict_consecutive
from cylsfm.model import Predictor


def _translation(step: np.ndarray) -> np.ndarray:
    """The camera's motion of a step ``T_{j->j+1}`` in frame ``j``'s axes."""
    return invert(step)[:3, 3]


def _with(step: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return invert(m)


def _mixed(net: np.ndarray, true: np.ndarray, part: str) -> np.ndarray:
    """``net``'s steps with ``part`` (length, direction, rotation, direction+rotation) from ``true``."""
    scale = np.median([np.linalg.norm(_translation(s)) for s in net]) / np.median(
        [np.linalg.norm(_translation(s)) for s in true]
    )
    out = []
    for a, g in zip(net, true, strict=True):
        ta, tg = _translation(a), _translation(g)
        la, lg = np.linalg.norm(ta), np.linalg.norm(tg) * scale
        da, dg = ta / max(la, 1e-9), tg / max(np.linalg.norm(tg), 1e-9)
        rot = invert(g if "rotation" in part else a)[:3, :3]
        length = lg if part == "length" else la
        direction = dg if "direction" in part else da
        out.append(_with(a, rot, length * direction))
    return np.stack(out)


def _azel(t: np.ndarray) -> tuple[float, float]:
    """Azimuth ``atan2(x, z)`` and elevation ``atan2(y, hypot(x, z))`` of a translation, radians."""
    return float(np.arctan2(t[0], t[2])), float(np.arctan2(t[1], np.hypot(t[0], t[2])))


def _true_angle(net: np.ndarray, true: np.ndarray, which: int) -> np.ndarray:
    """``net``'s steps with the translation's azimuth (``which=0``) or elevation (1) of ``true``."""
    out = []
    for a, g in zip(net, true, strict=True):
        ta = _translation(a)
        ang, ang_true = list(_azel(ta)), _azel(_translation(g))
        ang[which] = ang_true[which]
        az, el = ang
        v = np.linalg.norm(ta) * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
        out.append(_with(a, invert(a)[:3, :3], v))
    return np.stack(out)


def _direction_errors(net: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``[n, 3]`` per step of at least 0.3 m: azimuth error, elevation error, yaw error (degrees)."""
    rows = []
    for a, g in zip(net, true, strict=True):
        if np.linalg.norm(_translation(g)) < 0.3:
            continue
        (az_a, el_a), (az_g, el_g) = _azel(_translation(a)), _azel(_translation(g))
        yaw = np.arctan2(a[0, 2], a[0, 0]) - np.arctan2(g[0, 2], g[0, 0])
        rows.append(np.degrees([az_a - az_g, el_a - el_g, yaw]))
    return np.array(rows).reshape(-1, 3)


def _constant_length(net: np.ndarray) -> np.ndarray:
    med = np.median([np.linalg.norm(_translation(s)) for s in net])
    return np.stack(
        [
            _with(s, invert(s)[:3, :3], _translation(s) * med / max(np.linalg.norm(_translation(s)), 1e-9))
            for s in net
        ]
    )


def _smoothed(net: np.ndarray, sigma: float) -> np.ndarray:
    t = np.stack([_translation(s) for s in net])
    idx = np.arange(len(t))
    w = np.exp(-0.5 * ((idx[:, None] - idx[None, :]) / sigma) ** 2)
    t = (w / w.sum(1, keepdims=True)) @ t
    return np.stack([_with(s, invert(s)[:3, :3], x) for s, x in zip(net, t, strict=True)])


def _fused(net1: np.ndarray, net2: np.ndarray, weight: float) -> np.ndarray:
    """Positions by least squares from the one-frame and two-frame steps (rotations chained from net1)."""
    c2w = chain_poses(net1)
    m = len(c2w)
    rows = [(j, j + 1, c2w[j, :3, :3] @ _translation(t), 1.0) for j, t in enumerate(net1)]
    rows += [(j, j + 2, c2w[j, :3, :3] @ _translation(t), weight) for j, t in enumerate(net2)]
    a = np.zeros((len(rows) + 1, m))
    b = np.zeros((len(rows) + 1, 3))
    for i, (p, q, d, w) in enumerate(rows):
        a[i, p], a[i, q], b[i] = -w, w, w * d
    a[-1, 0] = 1.0
    c2w[:, :3, 3] = np.linalg.lstsq(a, b, rcond=None)[0]
    return c2w


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint")
    ap.add_argument("--data", default="experiments/out/data")
    args = ap.parse_args()
    predictor = Predictor.from_checkpoint(args.checkpoint, "cpu")
    test = {name for name, _ in read_split(split_path(args.data, "test"), args.data)}
    scores: dict[str, list[float]] = {}
    errors: list[np.ndarray] = []
    for seq in scan_dataset(args.data):
        if seq.path.name not in test:
            continue
        images, gt = list(seq.images), seq.poses
        net = predict_consecutive(predictor, images, seq.camera, batch_size=16)
        true = np.stack([invert(gt[j + 1]) @ gt[j] for j in range(len(gt) - 1)])
        two = np.zeros((len(images) - 2, 4, 4))
        for off in (0, 1):
            for i, t in enumerate(predict_consecutive(predictor, images[off::2], seq.camera, batch_size=16)):
                two[off + 2 * i] = t
        base = snippet_ates(gt, chain_poses(net))
        variants = {"network": net, "constant length": _constant_length(net)}
        for part in ("length", "direction", "rotation", "direction+rotation"):
            variants[f"true {part}"] = _mixed(net, true, part)
        variants["true azimuth of the translation"] = _true_angle(net, true, 0)
        variants["true elevation of the translation"] = _true_angle(net, true, 1)
        errors.append(_direction_errors(net, true))
        for sigma in (1.0, 1.5, 2.0):
            variants[f"smoothed, sigma {sigma:g}"] = _smoothed(net, sigma)
        for name, val in [
            ("constant velocity", base["constant_velocity"]),
            ("zero motion", base["zero_motion"]),
        ]:
            scores.setdefault(name, []).extend(val)
        for name, steps in variants.items():
            scores.setdefault(name, []).extend(snippet_ates(gt, chain_poses(steps))["model"])
        for w in (0.5, 1.0):
            scores.setdefault(f"fused with 2-frame steps, w {w:g}", []).extend(
                snippet_ates(gt, _fused(net, two, w))["model"]
            )
    err = np.concatenate(errors)
    az, el, yaw = err.T
    print(
        f"per step (>= 0.3 m, {len(err)}): azimuth error mean {az.mean():+.2f} sd {az.std():.2f} deg, "
        f"elevation error mean {el.mean():+.2f} sd {el.std():.2f} deg; "
        f"correlation of the azimuth and yaw errors {np.corrcoef(az, yaw)[0, 1]:+.2f}\n"
    )
    cv = float(np.mean(scores["constant velocity"]))
    print("| | snippet ATE | / constant velocity |\n|---|---|---|")
    for name, val in scores.items():
        print(f"| {name} | {np.mean(val):.4f} | {np.mean(val) / cv:.3f}x |")


if __name__ == "__main__":
    torch.set_num_threads(2)
    main()
