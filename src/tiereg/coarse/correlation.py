"""Correlation kernels: the one home of phase correlation and masked normalized correlation.

Surfaces are in *full* mode unless asked otherwise: for a reference image of shape ``(Hr, Wr)``
and a moving image of shape ``(Hm, Wm)`` the surface has shape ``(Hr + Hm - 1, Wr + Wm - 1)`` and
index ``(i, j)`` stands for the shift ``u = (i - (Hm - 1), j - (Wm - 1))``: moving pixel ``p``
lands on reference pixel ``p + u``. Zero padding to that size means no circular wrap-around.
In *valid* mode (a reference at least as large as the moving image, e.g. a window around a
known position) only the shifts that keep the moving image inside the reference are computed:
shape ``(Hr - Hm + 1, Wr - Wm + 1)``, index ``(i, j)`` is the shift ``u = (i, j)``, and transforms
of ``(Hr, Wr)`` suffice, since those shifts never wrap around.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy import fft, ndimage

from ..grid import mask_bounds

_EPS = 100 * np.finfo(np.float64).eps


Mode = Literal["full", "valid"]


def surface_shape(ref_shape: tuple[int, int], mov_shape: tuple[int, int], *,
                  mode: Mode = "full") -> tuple[int, int]:
    if mode == "valid":
        return (ref_shape[0] - mov_shape[0] + 1, ref_shape[1] - mov_shape[1] + 1)
    return (ref_shape[0] + mov_shape[0] - 1, ref_shape[1] + mov_shape[1] - 1)


def shift_of_index(
    index: tuple[float, float], mov_shape: tuple[int, int], *, mode: Mode = "full"
) -> tuple[float, float]:
    """Surface index -> shift ``(d_row, d_col)`` of the moving image."""
    if mode == "valid":
        return (index[0], index[1])
    return (index[0] - (mov_shape[0] - 1), index[1] - (mov_shape[1] - 1))


class _Correlator:
    """Cross-correlations ``sum_p a(p + u) b(p)`` of many image pairs of two fixed shapes.

    Images may be stacks ``(..., rows, cols)``: the transforms run over the last two axes.
    """

    def __init__(self, ref_shape: tuple[int, int], mov_shape: tuple[int, int], *,
                 mode: Mode = "full", dtype: type = np.float64, trim: tuple[int, int] = (0, 0)):
        if mode == "valid" and (ref_shape[0] < mov_shape[0] or ref_shape[1] < mov_shape[1]):
            raise ValueError(f"valid mode needs a reference ({ref_shape}) at least as large as "
                             f"the moving image ({mov_shape})")
        self.ref_shape, self.mov_shape, self.mode, self.dtype = ref_shape, mov_shape, mode, dtype
        self.out = surface_shape(ref_shape, mov_shape, mode=mode)
        # full mode, trimmed: the period may be shorter by the trim, for the shifts that wrap
        # around onto the kept ones are shifts with no overlap at all (:func:`masked_ncc`)
        self.trim = (0, 0) if mode == "valid" else tuple(
            max(0, min(int(t), (n - 1) // 2)) for t, n in zip(trim, self.out))
        span = ref_shape if mode == "valid" else (self.out[0] - self.trim[0],
                                                  self.out[1] - self.trim[1])
        self.fft_shape = tuple(fft.next_fast_len(n, real=True) for n in span)

    def spectrum(self, image: np.ndarray) -> np.ndarray:
        """``rfft2`` of the image zero-padded to the transform's shape; the rows, one axis at a
        time: the padding rows are zero, so only the image's own rows need the first pass."""
        rows = fft.rfft(np.asarray(image, dtype=self.dtype), n=self.fft_shape[1], axis=-1)
        return fft.fft(rows, n=self.fft_shape[0], axis=-2, overwrite_x=True)

    def circular(self, spec_ref: np.ndarray, conj_mov: np.ndarray) -> np.ndarray:
        """The correlation at every shift of the transform's period (:meth:`to_full` orders
        and crops it): pointwise arithmetic can work on it first, and order the result once.
        ``conj_mov``: the complex conjugate of the moving image's spectrum (made once for the
        several correlations it takes part in)."""
        # one axis at a time: the same transform as ``irfft2``, measured a fifth faster
        columns = fft.ifft(spec_ref * conj_mov, axis=-2, overwrite_x=True)
        return fft.irfft(columns, n=self.fft_shape[1], axis=-1, overwrite_x=True)

    def to_full(self, circ: np.ndarray) -> np.ndarray:
        if self.mode == "valid":
            return circ[..., : self.out[0], : self.out[1]]
        hm, wm = self.mov_shape
        (tr, tc), (rows, cols) = self.trim, self.out
        rolled = np.roll(circ, (hm - 1 - tr, wm - 1 - tc), axis=(-2, -1))
        if (tr, tc) == (0, 0):
            return rolled[..., :rows, :cols]
        full = np.zeros((*circ.shape[:-2], rows, cols), dtype=circ.dtype)
        full[..., tr : rows - tr, tc : cols - tc] = rolled[..., : rows - 2 * tr, : cols - 2 * tc]
        return full


def cross_power_correlation(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    normalization: Literal["phase", "pomf", "none"] = "phase",
) -> np.ndarray:
    """Correlation surface from the cross-power spectrum, full mode.

    - ``"phase"``: symmetric phase-only matched filter / phase correlation (Kuglin & Hines 1975;
      Chen, Defrise & Deconinck 1994): ``C = F^-1{ F_r F_m* / |F_r F_m*| }``.
    - ``"pomf"``: phase-only matched filter (Horner & Gianino 1984, Appl. Opt. 23(6)): the
      moving image acts as the filter and keeps only its phase, ``C = F^-1{ F_r F_m* / |F_m| }``.
    - ``"none"``: plain cross-correlation ``C = F^-1{ F_r F_m* }``.
    """
    corr = _Correlator(reference.shape, moving.shape)
    fr = corr.spectrum(np.asarray(reference, dtype=np.float64))
    fm = corr.spectrum(np.asarray(moving, dtype=np.float64))
    cross = fr * np.conj(fm)
    if normalization == "phase":
        cross /= np.maximum(np.abs(cross), _EPS)
    elif normalization == "pomf":
        cross /= np.maximum(np.abs(fm), _EPS)
    elif normalization != "none":
        raise ValueError(f"unknown normalization {normalization!r}")
    return corr.to_full(fft.irfft2(cross, s=corr.fft_shape))


class MaskedReference:
    """A reference image and mask whose spectra are kept per FFT shape, for many correlations."""

    def __init__(self, image: np.ndarray, mask: np.ndarray):
        self.mask = np.asarray(mask, dtype=np.float64)
        self.image = np.where(self.mask > 0, image, 0.0)
        self.shape = self.image.shape
        self._spectra: dict[tuple, np.ndarray] = {}
        # the mask as a rectangle of data with holes in it (:func:`_frame_sums`)
        self.frame = mask_bounds(self.mask > 0) or (0, 0, 0, 0)
        r0, r1, c0, c1 = self.frame
        self.holes = np.argwhere(self.mask[r0:r1, c0:c1] <= 0) + (r0, c0)

    def spectrum(self, corr: _Correlator, which: str) -> np.ndarray:
        """The spectrum of the ``"image"``, its ``"square"`` or the ``"mask"``."""
        key = (which, corr.mov_shape, corr.fft_shape, corr.dtype)
        if key not in self._spectra:
            data = self.image * self.image if which == "square" else {
                "image": self.image, "mask": self.mask}[which]
            self._spectra[key] = corr.spectrum(data)
        return self._spectra[key]

    def sums_by_frame(self, mov_shape: tuple[int, int], fft_shape: tuple[int, int]) -> bool:
        """Whether the mask's correlations are cheaper as sums over its frame, less its holes
        (:func:`_frame_sums`), than as transforms: when correcting for the holes touches fewer
        cells than a surface holds (a reference with data everywhere but a few corners)."""
        return len(self.holes) * mov_shape[0] * mov_shape[1] <= fft_shape[0] * fft_shape[1]


def masked_ncc(
    reference: np.ndarray | MaskedReference,
    reference_mask: np.ndarray | None,
    moving: np.ndarray,
    moving_mask: np.ndarray,
    *,
    mode: Mode = "full",
    single: bool = False,
    trim: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray]:
    """Masked normalized cross-correlation at every shift (Padfield 2012, IEEE TIP 21(5)).

    Returns ``(ncc, overlap)``: the Pearson correlation of the two images over the cells valid in
    both, and the number of those cells, for every full-mode shift. With ``n = m_r * m_m``
    (correlation of the masks), ``S_r = (f_r m_r) * m_m``, ``S_m = m_r * (f_m m_m)`` (Padfield,
    eq. 17 ff.)::

        ncc = (sum f_r f_m - S_r S_m / n) / sqrt((sum f_r^2 - S_r^2/n) (sum f_m^2 - S_m^2/n))

    Shifts with fewer than 3 common cells, or a variance within the round-off of its sums, get
    ``ncc = 0``. ``single``: the transforms in single precision (float32), for sweeps that rank
    many hypotheses: about 1.5 times faster, and the NCC within 1e-4 of double precision (the
    sums are of band-passed values about zero, so their round-off stays small; measured in the
    tests); the surfaces then come back in float32. ``reference`` may be a
    :class:`MaskedReference` (then ``reference_mask`` is ignored) to reuse its spectra.
    ``moving`` and ``moving_mask`` may be a stack ``(k, rows, cols)`` of images of one shape
    (say, one per heading): then the surfaces are ``(k, ...)``, each as if computed alone.
    ``mode``: ``"full"`` or ``"valid"`` (module docstring). ``trim=(rows, cols)`` (full mode):
    the shifts within that many of either end of an axis are not computed (``ncc = n = 0``
    there), which shortens the transforms by as much (:func:`overlap_trim` gives the trim that
    leaves out only shifts with too little overlap to count).

    Three of the six sums correlate the reference's mask (``n``, ``S_m`` and the moving image's
    sum of squares). A reference with data everywhere in a rectangle but a few holes (a lidar
    grid, whose opening takes off its corners) gives them as sums over that rectangle less the
    holes, without transforms (:func:`_frame_sums`): 9 transforms a moving image become 5.
    """
    ref = reference if isinstance(reference, MaskedReference) else MaskedReference(
        reference, reference_mask)
    mm = np.asarray(moving_mask, dtype=np.float64)
    fm = np.where(mm > 0, moving, 0.0)
    dtype = np.float32 if single else np.float64
    corr = _Correlator(ref.shape, fm.shape[-2:], mode=mode, dtype=dtype, trim=trim)
    s_fr, s_fr2 = ref.spectrum(corr, "image"), ref.spectrum(corr, "square")
    c_fm, c_mm = (np.conj(sp, out=sp) for sp in map(corr.spectrum, (fm, mm)))
    sum_r = corr.circular(s_fr, c_mm)
    sum_rm = corr.circular(s_fr, c_fm)
    sum_rr = corr.circular(s_fr2, c_mm)
    # the sums over the moving image's cells that land on reference data
    if ref.sums_by_frame(corr.mov_shape, corr.fft_shape):
        n, sum_m, sum_mm = _frame_sums(corr, ref, (mm, fm, fm * fm))
    else:
        s_mr = ref.spectrum(corr, "mask")
        n = np.rint(corr.circular(s_mr, c_mm))
        sum_m = corr.circular(s_mr, c_fm)
        sum_mm = corr.circular(s_mr, np.conj(corr.spectrum(fm * fm)))
    # a variance within the round-off of its sums is no variance (a flat patch)
    tol = 1e3 * np.finfo(dtype).eps
    floor_rr = tol * np.abs(sum_rr).max(axis=(-2, -1), keepdims=True)
    floor_mm = tol * np.abs(sum_mm).max(axis=(-2, -1), keepdims=True)
    # the centred sums, in place where a sum is not needed again (arrays of the surfaces' size)
    inv_n = np.reciprocal(np.maximum(n, 1.0))
    mean_r = sum_r * inv_n
    mean_m = np.multiply(sum_m, inv_n, out=inv_n)
    num = np.subtract(sum_rm, mean_r * sum_m, out=sum_rm)
    var_r = np.subtract(sum_rr, np.multiply(mean_r, sum_r, out=mean_r), out=sum_rr)
    var_m = np.subtract(sum_mm, np.multiply(mean_m, sum_m, out=mean_m), out=sum_mm)
    varied = (var_r > floor_rr) & (var_m > floor_mm) & (n >= 3)
    denom = np.sqrt(np.multiply(var_r, var_m, out=var_r), out=var_r, where=varied)
    ncc = np.divide(num, denom, out=np.zeros_like(num), where=varied)
    return corr.to_full(np.clip(ncc, -1.0, 1.0, out=ncc)), corr.to_full(n)


def _frame_sums(corr: _Correlator, ref: MaskedReference,
                images: tuple[np.ndarray, ...]) -> list[np.ndarray]:
    """``sum_p m_r(p + u) b(p)`` for each moving image ``b``, at every index of the transform's
    period (as :meth:`_Correlator.circular` lays them out), without transforms: the sum of ``b``
    over the cells that land in the mask's frame (a box, by summed-area tables: Crow 1984),
    less its cells that land on the holes in it."""
    (hm, wm), (p0, p1) = corr.mov_shape, corr.fft_shape
    (a0, b0, a1, b1) = ref.frame
    # the shift each index of the period stands for: u, or u + period for a negative one
    u0 = np.arange(p0) - np.where(np.arange(p0) >= p0 - (hm - 1), p0, 0)
    u1 = np.arange(p1) - np.where(np.arange(p1) >= p1 - (wm - 1), p1, 0)
    # the moving rows (columns) r0 <= r < r1 that land in the frame at each shift
    r0 = np.clip(a0 - u0, 0, hm)
    r1 = np.maximum(np.clip(b0 - u0, 0, hm), r0)
    c0 = np.clip(a1 - u1, 0, wm)
    c1 = np.maximum(np.clip(b1 - u1, 0, wm), c0)
    starts = np.flatnonzero(r0)  # the rows whose sums start past the image's first row
    out = []
    for b in images:
        table = np.zeros((*b.shape[:-2], wm + 1, hm + 1))  # transposed: columns gather as rows
        np.cumsum(np.cumsum(b, axis=-1), axis=-2, out=table[..., 1:, 1:].swapaxes(-1, -2))
        by_cols = np.ascontiguousarray((table[..., c1, :] - table[..., c0, :]).swapaxes(-1, -2),
                                       dtype=corr.dtype)
        # less the rows above r0 where there are any (the table's row 0 is zero)
        sums = by_cols[..., r1, :]
        sums[..., starts, :] -= by_cols[..., r0[starts], :]
        # a hole at q is met by moving cell p at the shift q - p: the image, turned a half turn,
        # comes off the block of indices that ends at q (wrapping round the period)
        turned = np.ascontiguousarray(b[..., ::-1, ::-1], dtype=corr.dtype)
        for qr, qc in ref.holes:
            for rows, src_rows in _wrapped(qr - (hm - 1), hm, p0):
                for cols, src_cols in _wrapped(qc - (wm - 1), wm, p1):
                    sums[..., rows, cols] -= turned[..., src_rows, src_cols]
        out.append(sums)
    return out


def _wrapped(start: int, length: int, period: int) -> list[tuple[slice, slice]]:
    """The indices ``start .. start + length - 1`` modulo ``period`` as at most two slices
    ``(target, source)``."""
    start %= period
    first = min(length, period - start)
    parts = [(slice(start, start + first), slice(0, first))]
    if first < length:
        parts.append((slice(0, length - first), slice(first, length)))
    return parts


def overlap_trim(support: np.ndarray, min_overlap: float) -> tuple[int, int]:
    """The ``trim`` of :func:`masked_ncc` that leaves out only shifts at which less than
    ``min_overlap`` of the moving support (a stack: of each image's) can overlap the reference.

    At the ``t``-th shift from either end of an axis only the ``t`` outermost rows (columns) of
    the moving image overlap the reference; the cells they hold bound the overlap. A shift whose
    rows hold less than ``min_overlap`` of the support is left out, at both ends alike (the
    fewer of the two, and of a stack's images). Shortening the period by the trim wraps onto each
    kept shift only shifts beyond the far end, which overlap nothing.
    """
    support = np.asarray(support, bool).reshape(-1, *np.shape(support)[-2:])
    total = support.sum(axis=(-2, -1)).astype(np.float64)
    support, total = support[total > 0], total[total > 0]
    if len(total) == 0 or min_overlap <= 0:
        return (0, 0)
    need = (min_overlap - 1e-6) * total[:, None]  # a hair under: never trims a counted shift
    trim = []
    for axis in (-1, -2):  # row sums give the rows' trim, column sums the columns'
        lines = support.sum(axis=axis)
        first = np.argmax(np.cumsum(lines, axis=-1) >= need, axis=-1)
        last = np.argmax(np.cumsum(lines[:, ::-1], axis=-1) >= need, axis=-1)
        trim.append(int(min(first.min(), last.min())))
    return (trim[0], trim[1])


MAX_SCORED_NCC = 0.999  # keeps the Fisher transform finite


def match_score(ncc: np.ndarray, overlap: np.ndarray) -> np.ndarray:
    """How strongly a masked NCC over a share ``overlap`` of the block's cells speaks for a match.

    Fisher's z-transform, ``z = atanh(r) sqrt(n - 3)`` (Fisher 1921), is the significance of a
    correlation ``r`` over ``n`` samples; with ``n`` proportional to the overlap this is
    ``atanh(r) sqrt(overlap)`` up to a factor common to all hypotheses of one level. A partial
    overlap that correlates well beats a full overlap that correlates a little, which the plain
    ``r sqrt(overlap)`` gets wrong for high correlations.
    """
    r = np.clip(ncc, -MAX_SCORED_NCC, MAX_SCORED_NCC)
    return np.arctanh(r) * np.sqrt(np.clip(overlap, 0.0, 1.0))


def local_maxima(
    surface: np.ndarray, *, k: int, exclusion: int = 2, valid: np.ndarray | None = None
) -> list[tuple[int, int]]:
    """The ``k`` highest peaks, each at least ``exclusion`` cells from a higher one."""
    s = np.where(valid, surface, -np.inf) if valid is not None else surface.copy()
    s = np.asarray(s, dtype=np.float64).copy()
    peaks: list[tuple[int, int]] = []
    for _ in range(k):
        flat = int(np.argmax(s))
        if not np.isfinite(s.flat[flat]):
            break
        i, j = np.unravel_index(flat, s.shape)
        peaks.append((int(i), int(j)))
        s[max(0, i - exclusion) : i + exclusion + 1, max(0, j - exclusion) : j + exclusion + 1] = (
            -np.inf
        )
    return peaks


def second_peak(surface: np.ndarray, best: tuple[int, int], *, exclusion: int = 2) -> float:
    """The highest *local maximum* more than ``exclusion`` cells (Chebyshev) from ``best``.

    Only true local maxima count, so the shoulder of a broad main peak is not mistaken for a
    rival. Returns ``-inf`` when there is none.
    """
    s = np.where(np.isfinite(surface), surface, -np.inf)
    peaks = ndimage.maximum_filter(s, size=3, mode="constant", cval=-np.inf)
    is_max = (s == peaks) & np.isfinite(s)
    rows, cols = np.nonzero(is_max)
    far = np.maximum(np.abs(rows - best[0]), np.abs(cols - best[1])) > exclusion
    return float(s[rows[far], cols[far]].max()) if far.any() else float("-inf")


def subpixel_peak(surface: np.ndarray, peak: tuple[int, int]) -> tuple[float, float]:
    """Refine an integer peak by a 3-point parabola per axis: ``d = (c- - c+) / 2(c- - 2c0 + c+)``.

    The offset is clipped to half a cell; at the border, or beside a cell without a score
    (``-inf``), the integer position is kept.
    """
    out = []
    for axis in (0, 1):
        idx = list(peak)
        if idx[axis] == 0 or idx[axis] == surface.shape[axis] - 1:
            out.append(float(peak[axis]))
            continue
        lo, hi = list(idx), list(idx)
        lo[axis] -= 1
        hi[axis] += 1
        cm, c0, cp = surface[tuple(lo)], surface[tuple(idx)], surface[tuple(hi)]
        denom = cm - 2 * c0 + cp
        curved = np.isfinite(denom) and denom < 0
        d = float(np.clip((cm - cp) / (2 * denom), -0.5, 0.5)) if curved else 0.0
        out.append(peak[axis] + d)
    return out[0], out[1]


def peak_to_sidelobe(surface: np.ndarray, peak: tuple[int, int], *, exclude: int = 5) -> float:
    """Peak-to-sidelobe ratio ``(p - mean_SL) / std_SL`` (Bolme et al. 2010), window excluded."""
    mask = np.ones(surface.shape, bool)
    i, j = peak
    mask[max(0, i - exclude) : i + exclude + 1, max(0, j - exclude) : j + exclude + 1] = False
    side = surface[mask]
    if side.size < 2 or side.std() == 0:
        return 0.0
    return float((surface[peak] - side.mean()) / side.std())
