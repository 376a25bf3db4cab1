"""The table of experiments/precision.sh: held-out depth and pose of each run, inferred in fp32 and with the
networks in bf16, with the references that learned nothing.

    python experiments/precision_table.py experiments/out/amp-{true,false}-s{0,1}
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def main(runs: list[str]) -> None:
    print(
        "| training | seed | inference | abs_rel | a1 | snippet ATE | / const. vel. | APE rmse | rot. err turns (deg) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    refs = None
    for run in runs:
        path = Path(run)
        train = "bf16 (amp)" if "amp-true" in path.name else "fp32"
        seed = path.name.rsplit("-s", 1)[-1]
        for infer in ("fp32", "auto"):
            depth = json.loads((path / f"depth-{infer}.json").read_text())
            pose = json.loads((path / f"pose-{infer}.json").read_text())
            cv = pose["baselines"]["constant_velocity"]["ate_mean"]
            print(
                f"| {train} | {seed} | {'bf16' if infer == 'auto' else 'fp32'} | {depth['abs_rel']:.4f} | "
                f"{depth['a1']:.3f} | {pose['ate_mean']:.4f} | {pose['ate_mean'] / cv:.3f}x | "
                f"{pose['ape_rmse']:.3f} | {pose['motion']['model']['rot_err_deg_turning']:.3f} |"
            )
            refs = (depth["baselines"], pose["baselines"])
    if refs:
        d, p = refs
        print(
            f"references: constant depth abs_rel {d['constant']['abs_rel']:.4f}, per-row prior "
            f"{d['per_row']['abs_rel']:.4f}; constant velocity ATE {p['constant_velocity']['ate_mean']:.4f} "
            f"APE {p['constant_velocity']['ape_rmse']:.3f}; zero motion ATE {p['zero_motion']['ate_mean']:.4f}"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
