"""Adapters that run peer coarse-registration methods side by side with tiereg in a benchmark.

Each adapter runs a published method as its documentation shows, on the benchmark's inputs, and
converts its answer to our conventions; nothing is tuned beyond the documented usage. The only
preparation is what a user would do: fill NaN (no data) with the mean of the valid cells and pad
both rasters, each centred, to a common square of a power-of-two side.

Image-domain peers (rasters: a dense lidar REFERENCE grid and a sparse tie-point MOVING grid):

* ``imreg_dft`` -- the Fourier-Mellin method of Reddy & Chatterji (1996, IEEE Trans. Image
  Processing 5(8):1266-1271) as packaged by imreg_dft (M. Tyc, C. Gohlke):
  ``imreg_dft.similarity(ref, mov, numiter=3)``. Its result (``scale``, ``angle``, ``tvec``) is the
  transform ``imreg_dft.transform_img`` applies to the moving image to lay it onto the reference:
  put it centred into a 1.2x larger canvas, ``scipy.ndimage.zoom``, ``scipy.ndimage.rotate``
  (reshaping), ``scipy.ndimage.shift``, crop back centred. ``_imreg_dft_matrix`` composes these
  steps exactly (integer centring offsets included). It refuses scale changes outside (0.5, 2).
* ``skimage_fmt`` -- the scikit-image gallery example "Using Polar and Log-Polar Transformations
  for Registration" (doc/examples/registration/plot_register_rotation.py): difference of
  Gaussians band-pass (sigmas 5, 20 for the example's 1411-pixel image, scaled here in
  proportion to the padded side N), Hann window, log-polar warp (radius N // 8) of the centred
  FFT magnitudes, phase correlation (upsample 10) for rotation and scale. The example stops
  there; as it suggests ("first correct for rotation and scaling, then solve for translation"),
  rotation and scale are undone on the moving image and the translation found with the masked
  phase correlation of ``phase_cross_correlation`` (Padfield 2010; NaN cells masked; whole
  pixels). The spectrum cannot tell theta from theta + 180 deg: both are tried and the one whose
  registered overlap correlates better (Pearson r, reported as ``score``) wins.

Point-domain peer:

* ``open3d_fpfh_ransac`` -- Open3D's documented global registration
  (examples/python/pipelines/global_registration.py, "Global registration" tutorial): voxel
  down-sampling, normals, FPFH features (Rusu et al. 2009, ICRA, "Fast Point Feature Histograms
  (FPFH) for 3D registration"), RANSAC on mutual feature matches with a scaled point-to-point
  estimator. Both clouds are centred on their own centroids first (coordinates may be in the
  millions); the centring is folded back into ``T_ref_mov``. Open3D is optional: without it the
  adapter returns a failure note.

Conventions. Pixels are array indices (row, col) with pixel centres at integer indices.
``H_ref_mov`` maps a moving pixel to the reference pixel showing the same ground:
``[r_ref, c_ref, 1] = H_ref_mov @ [r_mov, c_mov, 1]``, a similarity
``H[:2, :2] = s * [[cos a, -sin a], [sin a, cos a]]`` (see ``similarity_matrix``). With row 0 at
the top of the screen, a positive angle ``a`` turns the moving content counter-clockwise as it
goes to the reference; ``s > 1`` means a moving pixel covers ``s`` reference pixels. For points,
``T_ref_mov`` (4x4) maps homogeneous moving (x, y, z, 1) to reference coordinates. A failed
peer returns the identity, ``score=None`` and the exception in ``note``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

_SWAP = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # (row, col) <-> (x, y)


@dataclass(frozen=True)
class PeerEstimate:
    H_ref_mov: np.ndarray  # 3x3, moving (row, col, 1) -> reference (row, col, 1)
    seconds: float
    score: float | None  # the peer's own confidence, if any
    note: str = ""


@dataclass(frozen=True)
class PointEstimate:
    T_ref_mov: np.ndarray  # 4x4, moving (x, y, z, 1) -> reference (x, y, z, 1)
    seconds: float
    score: float | None  # Open3D fitness (inlier fraction of the down-sampled source)
    note: str = ""


# --- conventions --------------------------------------------------------------------------------

def similarity_matrix(angle_deg: float, scale: float, shift=(0.0, 0.0), centre=(0.0, 0.0)):
    """H turning by ``angle_deg`` and scaling by ``scale`` about ``centre``, then shifting."""
    a = math.radians(angle_deg)
    H = np.eye(3)
    H[:2, :2] = scale * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    c = np.asarray(centre, float)
    H[:2, 2] = c - H[:2, :2] @ c + np.asarray(shift, float)
    return H


def similarity_params(H: np.ndarray) -> tuple[float, float]:
    """(angle in degrees, scale) of a 2-D similarity H (its translation is ``H[:2, 2]``)."""
    return math.degrees(math.atan2(H[1, 0], H[0, 0])), math.hypot(H[0, 0], H[1, 0])


def _translate(t) -> np.ndarray:
    T = np.eye(3)
    T[:2, 2] = t
    return T


def _prepare(ref: np.ndarray, mov: np.ndarray):
    """Pad both (each centred) to an N x N square, N a power of two; NaN -> mean of valid cells.

    Returns the filled squares, their validity masks and the offsets of each input in its square.
    """
    n = 1 << math.ceil(math.log2(max(*ref.shape, *mov.shape)))
    out = []
    for img in (ref, mov):
        img = np.asarray(img, np.float64)
        valid = np.isfinite(img)
        if not valid.any():
            raise ValueError("image has no valid cell")
        off = ((n - img.shape[0]) // 2, (n - img.shape[1]) // 2)
        square = np.full((n, n), img[valid].mean())
        mask = np.zeros((n, n), bool)
        sl = (slice(off[0], off[0] + img.shape[0]), slice(off[1], off[1] + img.shape[1]))
        square[sl] = np.where(valid, img, square[sl])
        mask[sl] = valid
        out.append((square, mask, off))
    return out


def _unpad(H_square: np.ndarray, off_ref, off_mov) -> np.ndarray:
    return _translate(-np.asarray(off_ref, float)) @ H_square @ _translate(off_mov)


def _run(fn, *args):
    """Time ``fn(*args) -> (H, score, note)``; turn any exception into a failure estimate."""
    start = time.perf_counter()
    try:
        H, score, note = fn(*args)
    except Exception as exc:  # noqa: BLE001 -- a peer failing is a result to report
        return PeerEstimate(np.eye(3), time.perf_counter() - start, None,
                            f"{type(exc).__name__}: {exc}")
    return PeerEstimate(H, time.perf_counter() - start, score, note)


# --- imreg_dft ----------------------------------------------------------------------------------

def _embed_offset(dst: int, src: int) -> int:
    """Index shift ``imreg_dft.utils.embed_to`` applies when centring ``src`` cells in ``dst``."""
    return (dst - src) // 2 if dst >= src else -((src - dst) // 2)


def _imreg_dft_matrix(shape, scale: float, angle: float, tvec) -> np.ndarray:
    """The (row, col) map of ``imreg_dft.transform_img(img, scale, angle, tvec)``, step by step."""
    shape = np.asarray(shape, int)
    big = np.round(shape * 1.2).astype(int)
    H = _translate([_embed_offset(b, s) for b, s in zip(big, shape)])
    if scale != 1.0:  # ndimage.zoom: output shape round(in * z), corner pixels to corner pixels
        zoomed = np.array([round(b * scale) for b in big])
        H = np.diag([*((zoomed - 1) / (big - 1)), 1.0]) @ H
        big = zoomed
    if angle != 0.0:  # ndimage.rotate(reshape=True): in = R (out - c_out) + c_in
        c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))
        R = np.array([[c, s], [-s, c]])
        bounds = R @ [[0, 0, big[0], big[0]], [0, big[1], 0, big[1]]]
        rotated = (np.ptp(bounds, axis=1) + 0.5).astype(int)
        M = np.eye(3)
        M[:2, :2] = R.T
        H = _translate((rotated - 1) / 2) @ M @ _translate(-(big - 1) / 2) @ H
        big = rotated
    H = _translate(tvec) @ H  # ndimage.shift
    return _translate([_embed_offset(s, b) for s, b in zip(shape, big)]) @ H


def _imreg_dft(ref, mov):
    import imreg_dft

    (ref_sq, _, off_ref), (mov_sq, _, off_mov) = _prepare(ref, mov)
    res = imreg_dft.similarity(ref_sq, mov_sq, numiter=3)
    H = _imreg_dft_matrix(ref_sq.shape, res["scale"], res["angle"], res["tvec"])
    return _unpad(H, off_ref, off_mov), float(res["success"]), ""


def run_imreg_dft(ref: np.ndarray, mov: np.ndarray) -> PeerEstimate:
    """imreg_dft's Fourier-Mellin similarity registration of ``mov`` onto ``ref``."""
    return _run(_imreg_dft, ref, mov)


# --- scikit-image example -----------------------------------------------------------------------

_EXAMPLE_SIDE = 1411  # side of skimage.data.retina(), the image the example's sigmas are for


def _warp_into(img, H_out_in, shape, order):
    """Resample ``img`` so that output pixel p shows ``img`` at ``H_out_in^-1 p``."""
    from skimage.transform import ProjectiveTransform, warp

    inv = _SWAP @ np.linalg.inv(H_out_in) @ _SWAP  # skimage maps (x=col, y=row)
    return warp(img.astype(np.float64), ProjectiveTransform(inv), output_shape=shape,
                order=order, mode="constant", cval=0.0, preserve_range=True)


def _overlap_r(ref, ref_mask, mov, mov_mask, H):
    """Pearson correlation of ``ref`` and ``mov`` warped by H, over their common valid cells."""
    warped = _warp_into(mov, H, ref.shape, 1)
    both = ref_mask & (_warp_into(mov_mask, H, ref.shape, 0) > 0.5)
    if both.sum() < 10:
        return -1.0
    r = np.corrcoef(ref[both], warped[both])[0, 1]
    return float(r) if np.isfinite(r) else -1.0


def _skimage_fmt(ref, mov):
    from scipy.fft import fft2, fftshift
    from skimage.filters import difference_of_gaussians, window
    from skimage.registration import phase_cross_correlation
    from skimage.transform import warp_polar

    (ref_sq, ref_mask, off_ref), (mov_sq, mov_mask, off_mov) = _prepare(ref, mov)
    shape = ref_sq.shape
    hann = window("hann", shape)
    k = shape[0] / _EXAMPLE_SIDE  # the example's band-pass, scaled to this image size
    spectra = [np.abs(fftshift(fft2(difference_of_gaussians(img, 5 * k, 20 * k) * hann)))
               for img in (ref_sq, mov_sq)]
    radius = shape[0] // 8  # only the lower frequencies, as in the example
    polar = [warp_polar(fs, radius=radius, output_shape=shape, scaling="log", order=0)
             [: shape[0] // 2] for fs in spectra]  # half of the (symmetric) spectrum
    shifts, error, _ = phase_cross_correlation(polar[0], polar[1], upsample_factor=10,
                                               normalization=None)
    theta = 360.0 / shape[0] * shifts[0]  # moving turned by theta (counter-clockwise) ...
    scale = math.exp(shifts[1] / (shape[1] / math.log(radius)))  # ... and enlarged by scale
    centre = ((shape[0] - 1) / 2, (shape[1] - 1) / 2)
    best = None
    for angle in (-theta, 180.0 - theta):  # undo it; the spectrum is blind to +180 deg
        H_rs = similarity_matrix(angle, 1.0 / scale, centre=centre)
        turned = _warp_into(mov_sq, H_rs, shape, 1)
        turned_mask = _warp_into(mov_mask, H_rs, shape, 0) > 0.5
        shift = phase_cross_correlation(ref_sq, turned, reference_mask=ref_mask,
                                        moving_mask=turned_mask)[0]
        H = _translate(shift) @ H_rs
        r = _overlap_r(ref_sq, ref_mask, mov_sq, mov_mask, H)
        if best is None or r > best[1]:
            best = (H, r)
    note = f"log-polar phase-correlation error {float(error):.3f}"
    return _unpad(best[0], off_ref, off_mov), best[1], note


def run_skimage_fmt(ref: np.ndarray, mov: np.ndarray) -> PeerEstimate:
    """The scikit-image log-polar FFT registration example, plus masked translation."""
    return _run(_skimage_fmt, ref, mov)


PEERS_IMAGE = {"imreg_dft": run_imreg_dft, "skimage_fmt": run_skimage_fmt}


# --- Open3D -------------------------------------------------------------------------------------

def run_open3d_fpfh_ransac(moving_xyz: np.ndarray, reference_xyz: np.ndarray, *, voxel: float,
                           seed: int | None = None) -> PointEstimate:
    """Open3D's FPFH + RANSAC global registration (with scaling) of moving onto reference.

    ``voxel`` is the down-sampling size for both clouds, in their units; ``seed``, if given,
    seeds Open3D's random generator for a repeatable run.
    """
    start = time.perf_counter()
    try:
        import open3d as o3d
    except Exception as exc:  # noqa: BLE001 -- optional dependency or its libraries missing
        return PointEstimate(np.eye(4), time.perf_counter() - start, None,
                             f"Open3D unavailable: {type(exc).__name__}: {exc}")
    reg = o3d.pipelines.registration
    try:
        if seed is not None:
            o3d.utility.random.seed(seed)
        clouds, centres = [], []
        for xyz in (moving_xyz, reference_xyz):
            xyz = np.asarray(xyz, np.float64)
            centre = xyz.mean(axis=0)
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz - centre))
            pcd = pcd.voxel_down_sample(voxel)
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
            fpfh = reg.compute_fpfh_feature(
                pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
            clouds.append((pcd, fpfh))
            centres.append(centre)
        (src, src_fpfh), (tgt, tgt_fpfh) = clouds
        result = reg.registration_ransac_based_on_feature_matching(
            src, tgt, src_fpfh, tgt_fpfh, True, 1.5 * voxel,
            reg.TransformationEstimationPointToPoint(True), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
    except Exception as exc:  # noqa: BLE001
        return PointEstimate(np.eye(4), time.perf_counter() - start, None,
                             f"{type(exc).__name__}: {exc}")
    shift_to, shift_from = np.eye(4), np.eye(4)
    shift_to[:3, 3], shift_from[:3, 3] = centres[1], -centres[0]
    T = shift_to @ np.asarray(result.transformation) @ shift_from
    note = (f"{len(src.points)} source / {len(tgt.points)} target points after down-sampling, "
            f"{len(result.correspondence_set)} inliers, inlier RMSE {result.inlier_rmse:.3g}")
    return PointEstimate(T, time.perf_counter() - start, float(result.fitness), note)
