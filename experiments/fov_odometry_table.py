"""The field-of-view table with refinement, from the ``table.json`` files of ``experiments/odometry.py``.

Usage: ``python experiments/fov_odometry_table.py TABLE_JSON[:LABEL] ...`` (see ``experiments/fov_odometry.sh``).
One row per field of view for the refined trajectory and one for the pose network alone (mean over the test
rides of the whole-ride APE after Sim(3) alignment, its ratio to constant velocity, the RPE, the rotation
error per frame over all and over turning steps, the direction error of the translation per frame); constant
velocity and the visual compass (full panorama only: it needs the whole circle) of the first table last.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from cylsfm.evaluate.tables import markdown_row, markdown_rule

COLUMNS = ["APE rmse", "APE / const. vel.", "RPE trans", "rot. err deg", "rot. err turns", "dir. err deg"]


def _row(label: str, m: dict, cv: dict) -> str:
    return markdown_row(
        label,
        [
            m["ape_rmse"],
            m["ape_rmse"] / cv["ape_rmse"],
            m["rpe_trans_rmse"],
            m["rot_err_deg_mean"],
            m["rot_err_deg_turning"],
            m["dir_err_deg_mean"],
        ],
    )


def main(argv: list[str]) -> None:
    lines = [markdown_row("", COLUMNS), markdown_rule(len(COLUMNS))]
    first = None
    for arg in argv:
        path, _, label = arg.partition(":")
        if not Path(path).is_file():
            continue
        rows = json.loads(Path(path).read_text())["refine"]
        first = first or rows
        cv = rows["constant_velocity"]
        lines.append(_row(f"{label}, refined", rows["refined"], cv))
        lines.append(_row(f"{label}, network alone", rows["network"], cv))
    if first is not None:
        lines.append(_row("constant velocity", first["constant_velocity"], first["constant_velocity"]))
        lines.append(
            _row("visual compass (360 degrees) + network step", first["compass"], first["constant_velocity"])
        )
    print("\n".join(lines))


if __name__ == "__main__":
    main(sys.argv[1:])
