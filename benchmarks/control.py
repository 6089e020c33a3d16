"""Lidar control points against the true surface, on the fine benchmark's simulated scenes.

For each scene kind and case of ``benchmarks/fine.py`` (same worlds, lidar and blocks), the tie
points are registered (coarse + fine; where the coarse stage declines, as on farmland, the fine
stage starts from the truth disturbed by a typical coarse error) and the control points are
selected. Their lidar-derived heights are compared with the world's true surface at their
positions. Target: at least 95 % within 0.1 m.

    python benchmarks/control.py     # -> benchmarks/results/control.md (after fine.py made the lidar)
"""

from __future__ import annotations

import datetime
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from fine import CASES_PER_KIND, kind_setup, perturbed  # noqa: E402

from tiereg import register  # noqa: E402
from tiereg.control import select_control_points  # noqa: E402
from tiereg.simulate import GEOREF, KINDS, make_scene  # noqa: E402

TOLERANCE_M, TARGET = 0.10, 0.95


def main() -> None:
    rows, errors = [], []
    for index, kind in enumerate(KINDS):
        k = kind_setup(index, kind)  # the fine benchmark's scenes and cases
        world, ref = k.world, k.ref
        for case, cs in k.cases(CASES_PER_KIND):
            scene = make_scene(cs, world=world, lidar=k.base.lidar)
            result = register(scene.moving, ref)
            start = "coarse"
            if not result.confident:
                result = register(scene.moving, ref, coarse="none",
                                  initial=perturbed(scene.T_ref_mov, scene.moving))
                start = "perturbed truth"
            cps = select_control_points(result.residuals.xyz - ref.origin, ref,
                                        blunder=result.residuals.blunder)
            if cps:
                xyz = np.array([p.xyz for p in cps])
                err = xyz[:, 2] - world.sample("dsm", xyz[:, 0] - GEOREF[0],
                                               xyz[:, 1] - GEOREF[1])
            else:
                err = np.empty(0)
            errors.append(err)
            within = float(np.mean(np.abs(err) <= TOLERANCE_M)) if len(err) else float("nan")
            rows.append((kind, case, start, len(scene.moving), len(cps),
                         sum(p.kind == "height" for p in cps), within,
                         float(np.median(np.abs(err))) if len(err) else float("nan")))
            print(f"{kind}-{case}: {len(cps)} control points, {within:.1%} within "
                  f"{TOLERANCE_M} m", file=sys.stderr)
    allerr = np.concatenate(errors)
    share = float(np.mean(np.abs(allerr) <= TOLERANCE_M)) if len(allerr) else float("nan")
    lines = ["# Lidar control points against the true surface", "",
             f"- date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}",
             "- scenes: the fine benchmark's (lidar 1 point per m^2, tie noise 0.15 m / 0.3 m)",
             f"- all scenes: {len(allerr)} control points, **{share:.1%}** within "
             f"{TOLERANCE_M} m of the true surface (target {TARGET:.0%}: "
             f"**{'met' if share >= TARGET else 'not met'}**)", "",
             "| scene | case | start | tie points | control points | height only | within 0.1 m "
             "| median abs error (m) |", "|---|---:|---|---:|---:|---:|---:|---:|"]
    for kind, case, start, n, m, h, w, med in rows:
        lines.append(f"| {kind} | {case} | {start} | {n} | {m} | {h} | "
                     f"{'-' if not m else f'{w:.1%}'} | {'-' if not m else f'{med:.3f}'} |")
    lines += ["", "Forest and mountains give few or no control points: their lidar patches are "
              "rough or steep, which the selection refuses by design."]
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "control.md").write_text("\n".join(lines) + "\n")
    print(HERE / "results" / "control.md")


if __name__ == "__main__":
    main()
