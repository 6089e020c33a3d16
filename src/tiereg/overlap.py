"""Do two data sets overlap, and where? The coarse registration's quick answer.

``check_overlap(moving, reference)`` runs the coarse stage only (no fine stage) and reports the
share of the tie points that land on the reference surface, the area they cover, its outline as
GeoJSON in the reference's coordinates, and how much the answer can be trusted: the coarse
stage's confidence. When the coarse stage finds no reliable registration the answer is "no
reliable overlap found": that is not proof of no overlap (featureless ground cannot be matched),
and the result says which.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from .grid import GridSpec
from .pipeline import PointsLike, RegistrationResult, register


@dataclass(frozen=True)
class OverlapResult:
    registration: RegistrationResult  # the coarse registration it rests on
    fraction: float  # share of the tie points on the reference surface
    area: float  # area of the overlap outline (reference units squared)
    outline: dict[str, Any]  # GeoJSON MultiPolygon, reference coordinates
    seconds: float  # the whole answer, reading the inputs included (``registration``'s
    # ``reference_seconds`` of it went to reading and gridding the reference)

    @property
    def confident(self) -> bool:
        return self.registration.confident

    @property
    def verdict(self) -> str:
        if not self.confident:
            return "no reliable overlap found"
        return f"overlap: {self.fraction:.0%} of the tie points lie on the reference"

    def to_dict(self) -> dict[str, Any]:
        r = self.registration
        return {"overlap_fraction": round(self.fraction, 4), "area": round(self.area, 3),
                "confident": r.confident, "confidence": round(r.confidence, 4),
                "verdict": self.verdict, "reasons": list(r.reasons),
                "T_ref_mov": r.T_ref_mov.matrix.tolist(), "units": r.inputs.units,
                "seconds": round(self.seconds, 3),
                "reference_seconds": round(r.reference_seconds, 3), "outline": self.outline}

    def to_geojson(self) -> str:
        props = {k: v for k, v in self.to_dict().items() if k not in ("outline", "T_ref_mov")}
        return json.dumps({"type": "FeatureCollection", "features": [
            {"type": "Feature", "properties": props, "geometry": self.outline}]}, indent=1)


def check_overlap(moving: PointsLike, reference: PointsLike, *, cell_size: float | None = None,
                  **options: Any) -> OverlapResult:
    """The overlap of ``moving`` with ``reference`` after a coarse registration (no fine stage).

    ``options`` go to :func:`tiereg.register` (``coarse``, ``moving_format``, ``progress`` ...).
    """
    t0 = time.perf_counter()
    result = register(moving, reference, fine="none", cell_size=cell_size, **options)
    assert result.residuals is not None
    on = np.isfinite(result.residuals.dz_after)  # the points the quality counts on the surface
    outline, area = overlap_outline(result.residuals.xyz[on, :2], result.cell_size)
    return OverlapResult(result, result.quality.overlap_fraction, area, outline,
                         time.perf_counter() - t0)


def overlap_outline(xy: np.ndarray, cell: float) -> tuple[dict[str, Any], float]:
    """The outline of the cells holding points (gaps of a cell or two closed), as GeoJSON."""
    if len(xy) == 0:
        return {"type": "MultiPolygon", "coordinates": []}, 0.0
    from affine import Affine
    from rasterio import features

    lo, hi = xy.min(axis=0), xy.max(axis=0)
    spec = GridSpec.from_bounds(lo[0], lo[1], hi[0], hi[1], cell, pad_cells=3,
                                max_cells=50_000_000)
    idx, inside = spec.cell_index(xy[:, 0], xy[:, 1])
    mask = np.zeros(spec.size, bool)
    mask[idx[inside]] = True
    mask = mask.reshape(spec.shape)
    mask = ndimage.binary_closing(mask, structure=np.ones((3, 3)), iterations=2)
    mask = ndimage.binary_fill_holes(mask)
    labels, n = ndimage.label(mask)
    if n > 1:  # stray points (blunders, a lone tie point) are not a part of the overlap
        sizes = np.bincount(labels.ravel())[1:]
        mask = np.isin(labels, 1 + np.flatnonzero(sizes >= max(4, 0.01 * sizes.max())))
    transform = Affine(cell, 0.0, spec.x0, 0.0, -cell, spec.y0)
    polygons = [geom["coordinates"] for geom, value in
                features.shapes(mask.astype(np.uint8), mask=mask, transform=transform)
                if value == 1]
    return {"type": "MultiPolygon", "coordinates": polygons}, float(mask.sum() * cell * cell)


def write_overlap(result: OverlapResult, out_dir) -> tuple[str, ...]:
    """``overlap.json``, ``overlap.geojson`` and ``overlap.png`` into ``out_dir``."""
    from pathlib import Path

    from .errors import OutputError
    from .io.base import atomic_output, write_text_atomic
    from .report.figures import overlap_picture

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the folder ({exc.strerror}); give a folder "
                          "you can write to") from None
    from ._json import dumps_json

    write_text_atomic(out / "overlap.json", dumps_json(result.to_dict()) + "\n")
    write_text_atomic(out / "overlap.geojson", result.to_geojson() + "\n")
    r = result.registration
    ref_xy = np.empty((0, 2))
    if r.reference is not None:
        ref_xy = (r.reference.base.cell_points(max_cells=100_000)[:, :2]
                  + r.reference.origin[:2])
    assert r.residuals is not None
    png = overlap_picture(ref_xy, r.residuals.xyz[:, :2], np.isfinite(r.residuals.dz_after),
                          result.outline, title=result.verdict, units=r.inputs.units)
    with atomic_output(out / "overlap.png") as tmp:
        tmp.write_bytes(png)
    return ("overlap.json", "overlap.geojson", "overlap.png")
