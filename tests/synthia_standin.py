"""A SYNTHIA-Seqs stand-in: a ride of the built-in street generator rendered as four 90-degree pinhole views
per frame and stereo side, written in the documented SYNTHIA layout (RGB, 16-bit centimetre depth in three
channels, ``CameraParams`` with intrinsics and column-major camera matrices in a chosen axis convention).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from cylsfm.data.io import save_png
from cylsfm.data.synth import SynthConfig
from cylsfm.data.synth.render import render_frame
from cylsfm.data.synth.town import StreetScene
from cylsfm.geometry import PinholeCamera

VIEWS = (("Omni_F", 0.0), ("Omni_R", 90.0), ("Omni_B", 180.0), ("Omni_L", 270.0))
#: A view's axes in the rig's frame (columns: the view's x right, y down, z forward; ``p_rig = R p_view``),
#: written out from the axes rather than taken from the stitcher: a view turned right (yaw 90) looks along
#: the rig's +x and its right hand points backwards (-z); one turned left (270) looks along -x.
VIEW_AXES = {
    0.0: np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
    90.0: np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    180.0: np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),
    270.0: np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
}
#: The axes a file's pose matrices are written in -> ours (x right, y down, z forward), as the diagonal of
#: ``S`` in ``S M S``, from what each convention means: ``y-up`` keeps x right and z forward with y up
#: (Unity); ``x-flip`` has x pointing left.
FILE_AXES = {
    "y-up": (1.0, -1.0, 1.0),
    "none": (1.0, 1.0, 1.0),
    "yz-flip": (1.0, -1.0, -1.0),
    "x-flip": (-1.0, 1.0, 1.0),
}
FOCAL, CX, CY, WIDTH, HEIGHT = 532.740352, 640.0, 380.0, 1280, 760
BASELINE = 0.8


def standin_camera(scale: float) -> PinholeCamera:
    """The views' camera: SYNTHIA's intrinsics scaled by ``scale``."""
    w, h = round(WIDTH * scale), round(HEIGHT * scale)
    return PinholeCamera(width=w, height=h, fx=FOCAL * scale, cx=CX * scale, fy=FOCAL * scale, cy=CY * scale)


def rig_poses(scene: StreetScene, frames: list[int], side: str) -> list[np.ndarray]:
    """Camera-to-world (our axes) of a side's rig for the scene frames ``frames``."""
    shift = np.eye(4)
    shift[0, 3] = BASELINE if side == "right" else 0.0
    return [scene.c2w[i] @ shift for i in frames]


def write_synthia_standin(
    root: Path,
    seq: str = "02",
    season: str = "SPRING",
    frames: tuple[int, ...] = (0, 1, 2, 2, 3, 4),
    sides: tuple[str, ...] = ("left",),
    convention: str = "y-up",
    scale: float = 0.075,
    seed: int = 5,
) -> tuple[StreetScene, dict[str, list[np.ndarray]]]:
    """Write ``root/SYNTHIA-SEQS-SEQ-SEASON`` and return the scene and each side's true rig poses (ours).

    ``frames`` are the scene's frames in order (a repeated one is a camera standing still).
    """
    scene = StreetScene.generate(seed, SynthConfig(frames=max(frames) + 1, speed=1.5, stop_probability=0.0))
    camera = standin_camera(scale)
    folder = root / f"SYNTHIA-SEQS-{seq}-{season}"
    params = folder / "CameraParams"
    params.mkdir(parents=True, exist_ok=True)
    (params / "intrinsics.txt").write_text(
        f"{FOCAL * scale}\n\n{CX * scale}\n\n{CY * scale}\n\n{BASELINE}\n", encoding="utf-8"
    )
    s = np.diag([*FILE_AXES[convention.removesuffix("-inv")], 1.0])
    truth = {}
    for side in sides:
        sub = "Stereo_Left" if side == "left" else "Stereo_Right"
        truth[side] = rig_poses(scene, list(frames), side)
        for k, rig in enumerate(truth[side]):
            for view, yaw in VIEWS:
                turn = np.eye(4)
                turn[:3, :3] = VIEW_AXES[yaw]
                c2w = rig @ turn
                image, depth = render_frame(replace(scene, c2w=c2w[None]), 0, camera)
                name = f"{k:06d}"
                save_png(_mk(folder / "RGB" / sub / view / f"{name}.png"), image)
                cm = np.where(depth > 0, np.round(depth * 100), 65535).clip(0, 65535).astype(np.uint16)
                cv2.imwrite(str(_mk(folder / "Depth" / sub / view / f"{name}.png")), np.stack([cm] * 3, -1))
                m = s @ c2w @ s
                if convention.endswith("-inv"):
                    m = np.linalg.inv(m)
                line = " ".join(f"{v:.9g}" for v in m.T.reshape(-1))
                _mk(params / sub / view / f"{name}.txt").write_text(line + "\n", encoding="utf-8")
    return scene, truth


def _mk(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path
