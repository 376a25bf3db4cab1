"""The web viewer as a user sees it, in headless Chromium: the share of black pixels and the detail of the
picture, for today's viewer and for one built as the viewer was before (the texture and the vertices at
the network's 256x64): the figures behind RESULTS.md's viewer section.

Usage::

    python experiments/viewer_check.py OUT [--checkpoint RUN]

The scene: a synthetic street panorama at 1024x256 (``cylsfm synth``, seed 3) with its true depth brought
down to 256x64 (what a network of the demo's size gives); with ``--checkpoint``, also a 2048x1024
equirectangular panorama with the model's depth. Each page is rendered at 480x320 looking ahead, turned,
up and down; black: every channel at most 8 (the page's background); detail: the mean squared difference of
neighbouring grey values below the caption.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
from pathlib import Path

import numpy as np
from PIL import Image

from cylsfm.cli import main as cylsfm
from cylsfm.data.io import load_depth
from cylsfm.data.synth import generate_dataset

VIEWS = {"ahead": "", "turned": "#drag=200,0", "up": "#drag=0,300", "down": "#drag=0,-300"}


def screenshot(page: Path, target: Path, fragment: str) -> np.ndarray:
    browser = next(b for b in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if b)
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader"]
    cmd += ["--use-angle=swiftshader", "--disable-background-networking", "--no-first-run"]
    cmd += [f"--screenshot={target}", "--window-size=480,320", "--virtual-time-budget=8000"]
    subprocess.run([*cmd, page.as_uri() + fragment], check=True, capture_output=True, timeout=180)
    with Image.open(target) as im:
        return np.asarray(im.convert("RGB")).astype(np.float64)


def measure(page: Path, shots: Path) -> dict[str, tuple[float, float]]:
    out = {}
    for name, fragment in VIEWS.items():
        shot = screenshot(page / "index.html", shots / f"{page.name}-{name}.png", fragment)
        grey = shot[100:].mean(2)
        detail = float((np.diff(grey, axis=0) ** 2).mean() + (np.diff(grey, axis=1) ** 2).mean())
        out[name] = (float((shot.max(2) <= 8).mean()), detail)
    return out


def run(out: Path, checkpoint: str | None) -> None:
    generate_dataset(out / "data", sequences=1, frames=3, width=1024, height=256, seed=3, progress=False)
    seq = out / "data" / "seq_000"
    np.save(out / "small.npy", load_depth(seq / "depth" / "000000.npy")[1::4, 1::4])
    args = ["export", "viewer", str(seq / "images" / "000000.png"), "--depth", str(out / "small.npy")]
    pages = {"today": out / "today", "network-size": out / "network-size"}
    cylsfm([*args, str(pages["today"])])
    cylsfm([*args, str(pages["network-size"]), "--texture-width", "256", "--vertices", str(256 * 64)])
    if checkpoint:
        generate_dataset(
            out / "equirect", sequences=1, frames=3, width=2048, height=1024, seed=5,
            projection="equirect", progress=False,
        )  # fmt: skip
        pano = out / "equirect" / "seq_000" / "images" / "000000.png"
        pages["checkpoint"] = out / "checkpoint"
        cylsfm(["export", "viewer", str(pano), str(pages["checkpoint"]), "--checkpoint", checkpoint])
    shots = out / "shots"
    shots.mkdir(parents=True, exist_ok=True)
    print("| page | " + " | ".join(f"{v}: black, detail" for v in VIEWS) + " |")
    print("|---|" + "---|" * len(VIEWS))
    for name, page in pages.items():
        m = measure(page, shots)
        print(f"| {name} | " + " | ".join(f"{b:.2%}, {d:.1f}" for b, d in m.values()) + " |")


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("--checkpoint")
    a = p.parse_args()
    run(a.out, a.checkpoint)
