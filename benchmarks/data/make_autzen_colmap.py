"""Make ``src/tiereg/data/autzen_colmap/``: a COLMAP model of twelve images rendered over the
shipped Autzen lidar sample, and its truth.

    .venv/bin/python benchmarks/data/make_autzen_colmap.py --source PATH/TO/autzen-als-2010

``--source`` is a folder holding PDAL's ``autzen.jpg`` and ``autzen.wld`` (the RGB orthophoto
of the area, 1 ft pixels, EPSG:2994; PDAL ``test/data/autzen/``). Steps:

1. Surface: the first returns of ``src/tiereg/data/autzen_trim.laz`` (feet), interpolated
   linearly (``scipy.interpolate.griddata``; nearest return outside their hull) at the centres
   of a 2 ft grid over the file's extent: a DSM in the LAZ's own coordinates.
2. Texture: ``autzen.jpg`` (RGB), placed by its world file, resampled to 0.5 ft with a fixed
   fine random texture added (``sfm_render.make_texture``: the image has 1 ft pixels, the
   rendering 0.35 ft).
3. Images: two strips of six 768 x 1024 RGB images (portrait: the long side along the flight,
   so that the block spans 1,075 ft of the 1,177 ft strip) flown east and west (60 % forward,
   35 % side overlap, a few degrees of attitude noise), pinhole camera f = 1100 px with
   k1 = -0.06, k2 = 0.015, 385 ft above the median ground: GSD 0.35 ft (``sfm_render``).
4. pycolmap: SIFT (at most 3,000 features per image, to keep ``images.bin`` small),
   exhaustive matching, incremental mapping,
   one RADIAL camera (``sfm_reconstruct.reconstruct``). The model with the most images is copied
   unchanged (COLMAP's gauge and orientation) into ``src/tiereg/data/autzen_colmap/``.
5. ``truth.json``: the similarity from the model to the LAZ's frame fitted to where the model
   points' observations, cast through the true cameras, meet the surface
   (``sfm_reconstruct.compute_truth``), with its residuals; GSD in feet; and a check against
   the lidar itself: the mapped points' heights minus the nearest first returns'.

Everything random is seeded: a rerun gives the same images; pycolmap's result may differ in
the last digits from one machine or version to another.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
BENCH = HERE.parent
sys.path.insert(0, str(BENCH))

from sfm_reconstruct import compute_truth, reconstruct  # noqa: E402
from sfm_render import (  # noqa: E402
    Camera,
    FlightPlan,
    HeightField,
    Texture,
    make_texture,
    plan_block,
    render_image,
)

REPO = BENCH.parent
LAZ = REPO / "src" / "tiereg" / "data" / "autzen_trim.laz"
OUT = REPO / "src" / "tiereg" / "data" / "autzen_colmap"
WORK = BENCH / "work" / "sfm" / "autzen-trim"
DSM_CELL_FT = 2.0
PLAN = FlightPlan(strips=2, images_per_strip=6, gsd=0.35, forward_overlap=0.6, side_overlap=0.35,
                  heading_deg=90.0)
# portrait images (the long side along the flight) so that the block spans most of the strip
CAMERA = Camera(width_px=768, height_px=1024, focal_px=1100.0, k1=-0.06, k2=0.015)
MAX_FEATURES = 3000  # keeps the model's images.bin small
SEED = 2994


def surface() -> HeightField:
    """The DSM of the LAZ's first returns on a 2 ft grid, as a height field (feet)."""
    import laspy
    from scipy.interpolate import griddata

    las = laspy.read(LAZ)
    first = np.asarray(las.return_number) == 1
    x, y, z = (np.asarray(v, dtype=np.float64)[first] for v in (las.x, las.y, las.z))
    x0, y1 = np.floor(x.min()), np.ceil(y.max())
    cols = int(np.ceil((x.max() - x0) / DSM_CELL_FT))
    rows = int(np.ceil((y1 - y.min()) / DSM_CELL_FT))
    cx = x0 + (np.arange(cols) + 0.5) * DSM_CELL_FT
    cy = y1 - (np.arange(rows) + 0.5) * DSM_CELL_FT
    X, Y = np.meshgrid(cx, cy)
    dsm = griddata((x, y), z, (X, Y), method="linear")
    hole = np.isnan(dsm)
    dsm[hole] = griddata((x, y), z, (X[hole], Y[hole]), method="nearest")
    return HeightField(dsm, x0=x0, y0=y1, cell=DSM_CELL_FT)


def texture(source: Path, field_: HeightField) -> Texture:
    """``autzen.jpg`` over the DSM's extent (RGB, 0..1) with fine detail at 0.5 ft."""
    from PIL import Image

    a, _, _, e, cx, cy = (float(v) for v in (source / "autzen.wld").read_text().split())
    img = np.asarray(Image.open(source / "autzen.jpg").convert("RGB"), dtype=np.float32) / 255
    rows, cols = field_.h.shape
    left, top = field_.x0 - 50, field_.y0 + 50  # a margin of 50 ft
    c0 = int((left - cx) / a)
    r0 = int((top - cy) / e)
    c1 = int((field_.x0 + cols * field_.cell + 50 - cx) / a) + 1
    r1 = int((field_.y0 - rows * field_.cell - 50 - cy) / e) + 1
    crop = img[r0:r1, c0:c1]
    # the world file gives the centre of the upper-left pixel; the grid's corner is half out
    x0 = cx + c0 * a - a / 2
    y0 = cy + r0 * e - e / 2
    return make_texture(crop, x0=x0, y0=y0, cell=a, gsd=PLAN.gsd,
                        rng=np.random.default_rng([SEED, 1]))


def lidar_check(model: Path, T_ref_mov) -> dict:
    """Heights of the model's points mapped by the truth minus the median of the four nearest
    first returns of the LAZ (points with a return within 3 ft horizontally)."""
    import laspy
    from scipy.spatial import cKDTree

    from sfm_reconstruct import read_observations

    las = laspy.read(LAZ)
    first = np.asarray(las.return_number) == 1
    q = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])[first]
    p = T_ref_mov.apply(read_observations(model).xyz)
    dist, idx = cKDTree(q[:, :2]).query(p[:, :2], k=4)
    near = dist[:, 0] < 3.0
    dz = p[near, 2] - np.median(q[idx[near], 2], axis=1)
    med = float(np.median(dz))
    return {"n_points_near_a_return": int(near.sum()), "median_dz_ft": med,
            "nmad_dz_ft": float(1.4826 * np.median(np.abs(dz - med)))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, required=True,
                        help="folder with autzen.jpg and autzen.wld")
    args = parser.parse_args()
    from PIL import Image

    field_ = surface()
    tex = texture(args.source, field_)
    rng = np.random.default_rng(SEED)
    rows, cols = field_.h.shape
    centre = (field_.x0 + 0.5 * cols * field_.cell, field_.y0 - 0.5 * rows * field_.cell)
    poses = plan_block(PLAN, CAMERA, centre_xy=centre, ground_z=float(np.median(field_.h)),
                       rng=rng)
    images = WORK / "images"
    images.mkdir(parents=True, exist_ok=True)
    for pose in poses:
        img, miss = render_image(field_, tex, CAMERA, pose, rng=rng,
                                 gain=float(rng.uniform(0.92, 1.05)))
        if miss > 0.001:
            raise SystemExit(f"{pose.name}: {100 * miss:.2f} % of the rays leave the surface")
        Image.fromarray(img).save(images / pose.name)
    stats = reconstruct(images, WORK / "colmap", max_features=MAX_FEATURES)
    print(json.dumps(stats, indent=1))
    model = WORK / "colmap" / "model"
    gsd = float(np.median([(p.centre[2] - float(field_.height(p.centre[:1], p.centre[1:2])[0]))
                           / CAMERA.focal_px for p in poses]))
    truth = compute_truth(model, poses, CAMERA, field_, gsd=gsd, georef=np.zeros(3))
    OUT.mkdir(parents=True, exist_ok=True)
    for f in OUT.glob("*.bin"):  # the README stays
        f.unlink()
    for f in sorted(model.iterdir()):
        shutil.copy2(f, OUT / f.name)
    d = truth.to_dict()
    d.update(units="international feet (EPSG:2994), as autzen_trim.laz",
             true_camera=asdict(CAMERA), estimated_camera=stats["camera_params"],
             plan=asdict(PLAN), n_images=len(poses), n_registered=stats["n_registered"],
             reprojection_error_px=stats["reprojection_error_px"],
             lidar_check=lidar_check(model, truth.T_ref_mov))
    (OUT / "truth.json").write_text(json.dumps(d, indent=1) + "\n")
    print(json.dumps(d, indent=1))


if __name__ == "__main__":
    main()
