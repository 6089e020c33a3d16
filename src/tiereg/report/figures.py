"""The report's pictures (matplotlib, drawn off-screen): maps, histograms, coarse evidence.

Every function returns PNG bytes, so the report can embed them in one self-contained HTML file
and also write them beside it.
"""

from __future__ import annotations

import io
import math

import numpy as np

from .._optional import pyplot

DPI = 110


def _pyplot():
    return pyplot("the report")


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    _pyplot().close(fig)
    return buf.getvalue()


def nice_length(span: float) -> float:
    """A 1-2-5 length near a fifth of ``span`` (for scale bars)."""
    target = max(span / 5.0, 1e-12)
    power = 10.0 ** math.floor(math.log10(target))
    return max(m * power for m in (1.0, 2.0, 5.0) if m * power <= target)


def _scale_bar(ax, xy: np.ndarray, units: str) -> None:
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    length = nice_length(float(hi[0] - lo[0]) or 1.0)
    x0 = lo[0] + 0.04 * (hi[0] - lo[0])
    y0 = lo[1] + 0.04 * (hi[1] - lo[1])
    ax.plot([x0, x0 + length], [y0, y0], color="black", lw=3, solid_capstyle="butt")
    label = f"{length:g} {units}" if units and units != "unknown" else f"{length:g}"
    ax.text(x0 + length / 2, y0 + 0.015 * (hi[1] - lo[1]), label, ha="center", va="bottom",
            fontsize=8)


def height_difference_map(xy: np.ndarray, dz: np.ndarray, *, title: str, limit: float,
                          units: str, blunder: np.ndarray | None = None) -> bytes:
    """The points coloured by ``dz`` (diverging, symmetric at ``limit``), colour and scale bar.

    Coordinates are shown relative to the lower-left corner of the points (projected coordinates
    in the millions do not fit an axis label); the corner is in the caption.
    """
    plt = _pyplot()
    lo = np.floor(xy.min(axis=0))
    local = xy - lo
    span = np.maximum(local.max(axis=0), 1e-9)
    fig, ax = plt.subplots(figsize=(6.4, float(np.clip(5.2 * span[1] / span[0] + 1.2, 3.0, 7.5))))
    off = ~np.isfinite(dz)
    if off.any():
        ax.scatter(local[off, 0], local[off, 1], s=3, c="0.8", label="off the reference")
    on = ~off
    sc = ax.scatter(local[on, 0], local[on, 1], c=dz[on], s=6, cmap="RdBu_r", vmin=-limit,
                    vmax=limit)
    if blunder is not None and blunder.any():
        ax.scatter(local[blunder, 0], local[blunder, 1], s=18, facecolors="none",
                   edgecolors="black", linewidths=0.6, label="blunder")
    cb = fig.colorbar(sc, ax=ax, fraction=0.046, pad=0.04, extend="both")
    cb.set_label(f"lidar surface - tie point height ({units})")
    _scale_bar(ax, local, units)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(f"x - {lo[0]:.0f}")
    ax.set_ylabel(f"y - {lo[1]:.0f}")
    if off.any() or (blunder is not None and blunder.any()):
        ax.legend(loc="upper right", fontsize=7, markerscale=2)
    return _png(fig)


def residual_histogram(dz_before: np.ndarray, dz_after: np.ndarray, *, limit: float,
                       units: str) -> bytes:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.2, 3.4))
    bins = np.linspace(-limit, limit, 61)
    for dz, label, colour in ((dz_before, "before the fine stage", "0.6"),
                              (dz_after, "after", "tab:blue")):
        v = dz[np.isfinite(dz)]
        if len(v):
            ax.hist(np.clip(v, -limit, limit), bins=bins, histtype="step", lw=1.6,
                    color=colour, label=f"{label} ({len(v)} points)")
    ax.set_xlabel(f"lidar surface - tie point height ({units}); clipped at +/-{limit:.3g}")
    ax.set_ylabel("tie points")
    ax.legend(fontsize=8)
    return _png(fig)


def coarse_candidates(candidates: list[dict], chosen: dict | None, rival: dict | None) -> bytes:
    """The coarse stage's hypotheses in heading x scale, coloured by correlation score."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.2, 3.6))
    if candidates:
        k = np.array([c["kappa_deg"] % 360.0 for c in candidates])
        s = np.array([c["scale"] for c in candidates])
        v = np.array([c["score"] for c in candidates])
        sc = ax.scatter(k, s, c=v, cmap="viridis", s=30)
        fig.colorbar(sc, ax=ax, label="correlation score")
    for h, marker, label in ((chosen, "*", "chosen"), (rival, "x", "best rival")):
        if h:
            ax.scatter([h["kappa_deg"] % 360.0], [h["scale"]], marker=marker, s=160,
                       c="red" if marker == "*" else "black", label=label)
    ax.set_yscale("log")
    ax.set_xlim(0, 360)
    ax.set_xlabel("heading (deg)")
    ax.set_ylabel("scale (reference per moving unit)")
    ax.set_title("coarse stage: candidates verified against the lidar", fontsize=10)
    if chosen or rival:
        ax.legend(fontsize=8)
    return _png(fig)


def overlap_picture(reference_xy: np.ndarray, placed_xy: np.ndarray, on: np.ndarray,
                    outline: dict, *, title: str, units: str) -> bytes:
    """The reference's footprint (a thinned sample of its cells), the placed tie points (on and
    off the reference) and the overlap outline."""
    plt = _pyplot()
    allxy = np.vstack([reference_xy, placed_xy]) if len(reference_xy) else placed_xy
    lo = np.floor(allxy.min(axis=0))
    span = np.maximum(allxy.max(axis=0) - lo, 1e-9)
    fig, ax = plt.subplots(figsize=(6.4, float(np.clip(6.0 * span[1] / span[0], 3.0, 8.0))))
    if len(reference_xy):
        ax.scatter(*(reference_xy - lo).T, s=1, c="0.82", label="reference", rasterized=True)
    ax.scatter(*(placed_xy[~on] - lo).T, s=4, c="tab:orange", label="tie points off it")
    ax.scatter(*(placed_xy[on] - lo).T, s=4, c="tab:blue", label="tie points on it")
    for poly in outline.get("coordinates", []):
        ring = np.asarray(poly[0]) - lo
        ax.plot(ring[:, 0], ring[:, 1], c="black", lw=1.2)
    _scale_bar(ax, allxy - lo, units)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(f"x - {lo[0]:.0f}")
    ax.set_ylabel(f"y - {lo[1]:.0f}")
    ax.legend(loc="upper right", fontsize=7, markerscale=3)
    return _png(fig)


def correlation_surface(window: np.ndarray, cell: float, *, units: str) -> bytes:
    """The masked-NCC score around the answer: shifts of the registered tie points' grid against
    the reference, in reference units; the answer is at (0, 0)."""
    plt = _pyplot()
    half = (window.shape[0] // 2) * cell
    fig, ax = plt.subplots(figsize=(5.2, 4.4))
    shown = np.where(np.isfinite(window), window, np.nan)
    im = ax.imshow(shown, extent=(-half - cell / 2, half + cell / 2, -half - cell / 2,
                                  half + cell / 2), origin="upper", cmap="magma")
    fig.colorbar(im, ax=ax, label="match score: atanh(NCC) x sqrt(overlap)")
    r, c = np.unravel_index(int(np.nanargmax(shown)), shown.shape)
    ax.scatter([(c - window.shape[1] // 2) * cell], [-(r - window.shape[0] // 2) * cell],
               marker="+", s=120, c="cyan", label="peak")
    ax.scatter([0], [0], marker="o", s=60, facecolors="none", edgecolors="white",
               label="the answer")
    ax.set_xlabel(f"shift x ({units})")
    ax.set_ylabel(f"shift y ({units})")
    ax.set_title("coarse stage: correlation around the answer", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    return _png(fig)
