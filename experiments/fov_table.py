"""The field-of-view table (the paper's Table 2) from runs of ``experiments/fov.sh``.

Usage: ``python experiments/fov_table.py RUN_DIR[:LABEL] ...``, each RUN_DIR with the ``pose.json`` that
``cylsfm evaluate pose`` wrote. One row per run: snippet ATE, full-ride APE, rotation error per frame
(all and turning steps), yaw slope on turns, a standing camera's step, the swapped-source cosine, the
motion verdict and the depth's abs_rel (from ``depth.json``), each beside constant velocity of the same
rides; the visual compass of the first run's (full) panoramas last.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from cylsfm.evaluate.tables import markdown_row, markdown_rule

COLUMNS = [
    "snippet ATE",
    "ATE / const. vel.",
    "APE rmse",
    "APE / const. vel.",
    "rot. err deg",
    "rot. err turns",
    "yaw slope",
    "standing/step",
    "swapped cos",
    "measured",
    "depth abs_rel",
]


def _row(label: str, pose: dict, motion: dict, verdict: dict | None = None, depth: dict | None = None) -> str:
    cv = pose["baselines"]["constant_velocity"]
    cells = [
        pose["ate_mean"],
        pose["ate_mean"] / cv["ate_mean"],
        pose.get("ape_rmse"),
        pose["ape_rmse"] / cv["ape_rmse"] if pose.get("ape_rmse") and cv.get("ape_rmse") else None,
        motion.get("rot_err_deg"),
        motion.get("rot_err_deg_turning"),
        motion.get("yaw_slope"),
        motion.get("standing_ratio"),
        motion.get("swap_cosine"),
        ("yes" if verdict["measured"] else "no") if verdict else None,
        depth.get("abs_rel") if depth else None,
    ]
    return markdown_row(label, cells)


def main(argv: list[str]) -> None:
    lines = [markdown_row("", COLUMNS), markdown_rule(len(COLUMNS))]
    first = None
    for arg in argv:
        path, _, label = arg.partition(":")
        f = Path(path) / "pose.json"
        if not f.is_file():
            continue
        pose = json.loads(f.read_text())
        first = first or pose
        d = Path(path) / "depth.json"
        depth = json.loads(d.read_text()) if d.is_file() else None
        motion = pose["motion"]
        lines.append(_row(label or Path(path).name, pose, motion["model"], motion.get("verdict"), depth))
    if first is not None:
        cv = first["baselines"]["constant_velocity"]
        lines.append(
            _row(
                "constant velocity",
                cv | {"baselines": first["baselines"]},
                first["motion"]["constant_velocity"],
            )
        )
        if first["baselines"].get("compass"):
            compass = first["baselines"]["compass"] | {"baselines": first["baselines"]}
            lines.append(_row("visual compass (360 degrees)", compass, first["motion"]["compass"]))
    print("\n".join(lines))


if __name__ == "__main__":
    main(sys.argv[1:])
