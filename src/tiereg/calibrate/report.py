"""The calibration's report: one self-contained HTML page with the lidar residual maps before
and after, and each camera's distortion curve before and after (matplotlib, PNGs embedded)."""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import numpy as np

from .._optional import pyplot


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _residual_maps(result):
    plt = pyplot("the calibration report")

    r = result.residuals
    xyz, used = r["xyz"], r["check"] | r["control"] | r["control_before"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), sharex=True, sharey=True)
    lim = float(np.nanpercentile(np.abs(r["dz_before"][used]), 95)) if used.any() else 1.0
    for ax, key, title in zip(axes, ("dz_before", "dz_after"),
                              ("registered only", "after calibration")):
        sc = ax.scatter(xyz[used, 0] - xyz[:, 0].mean(), xyz[used, 1] - xyz[:, 1].mean(),
                        c=r[key][used], cmap="RdBu_r", vmin=-lim, vmax=lim, s=14)
        ax.scatter(xyz[r["check"], 0] - xyz[:, 0].mean(), xyz[r["check"], 1] - xyz[:, 1].mean(),
                   facecolors="none", edgecolors="k", s=30, linewidths=0.6)
        ax.set_title(f"height above the lidar plane, {title}")
        ax.set_aspect("equal")
        ax.set_xlabel("x from the block centre")
    axes[0].set_ylabel("y from the block centre")
    fig.colorbar(sc, ax=axes, label="dz (reference units); circled: check points")
    return fig


def _distortion(result):
    plt = pyplot("the calibration report")

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for cam in result.cameras:
        if "k1" not in cam.names:
            continue
        f = cam.value(cam.names[0])
        corner = np.hypot(cam.width_px / 2, cam.height_px / 2) / f
        rr = np.linspace(0, corner, 100)
        for after, style in ((False, "--"), (True, "-")):
            k1 = cam.value("k1", after=after)
            k2 = cam.value("k2", after=after) if "k2" in cam.names else 0.0
            ff = cam.value(cam.names[0], after=after)
            ax.plot(rr * f, ff * rr * (k1 * rr**2 + k2 * rr**4), style,
                    label=f"camera {cam.camera_id} {'after' if after else 'before'}")
    ax.set_xlabel("radius from the principal point (px)")
    ax.set_ylabel("radial distortion (px)")
    ax.grid(alpha=0.3)
    ax.legend()
    return fig


def write_calibration_report(result, folder: str | Path) -> Path:
    """Write ``report.html`` into ``folder``; returns its path."""
    plt = pyplot("the calibration report")

    from ..io.base import write_text_atomic

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    parts = [f"<h1>tiereg calibrate</h1><p>confident: <b>{'yes' if result.confident else 'no'}"
             "</b></p>"]
    parts += [f"<p>{html.escape(t)}</p>" for t in (*result.reasons, *result.warnings)]
    rows = []
    for cam in result.cameras:
        for n, b, a, s in zip(cam.names, cam.before, cam.after, cam.sigma):
            shown = "held" if cam.is_held(n) else ("" if s is None else f"{s:.3g}")
            rows.append(f"<tr><td>{cam.camera_id}</td><td>{n}</td><td>{b:.6g}</td>"
                        f"<td>{a:.6g}</td><td>{shown}</td></tr>")
    parts.append("<table border=1 cellpadding=4><tr><th>camera</th><th>parameter</th>"
                 "<th>before</th><th>after</th><th>sigma</th></tr>" + "".join(rows) + "</table>")
    cb, ca = result.check_before, result.check_after
    if cb is not None and ca is not None:
        parts.append(f"<p>check points ({result.n_check}): height RMSE {cb.rmse_z:.3f} -> "
                     f"{ca.rmse_z:.3f}; reprojection RMS {result.reprojection_rms_before_px:.3f}"
                     f" -> {result.reprojection_rms_after_px:.3f} px</p>")
    for make in ((_residual_maps,) if result.residuals else ()) + (_distortion,):
        fig = make(result)
        parts.append(f'<p><img src="data:image/png;base64,{_png(fig)}"></p>')
        plt.close(fig)
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>tiereg calibrate</title>"
            "</head><body style='font-family:sans-serif'>" + "\n".join(parts) + "</body></html>")
    write_text_atomic(out / "report.html", page + "\n")
    return out / "report.html"
