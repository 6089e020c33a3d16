"""Correlation kernels against slow, obvious references, and known shifts."""

from __future__ import annotations

import numpy as np
import pytest

from tiereg.coarse.correlation import (
    MaskedReference,
    cross_power_correlation,
    local_maxima,
    masked_ncc,
    match_score,
    overlap_trim,
    peak_to_sidelobe,
    shift_of_index,
    subpixel_peak,
)


def slow_masked_ncc(fr, mr, fm, mm):
    """Pearson correlation over the common valid cells at every shift, by loops."""
    hr, wr = fr.shape
    hm, wm = fm.shape
    out = np.zeros((hr + hm - 1, wr + wm - 1))
    count = np.zeros_like(out)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            du, dv = i - (hm - 1), j - (wm - 1)
            a, b = [], []
            for r in range(hm):
                for c in range(wm):
                    rr, cc = r + du, c + dv
                    if 0 <= rr < hr and 0 <= cc < wr and mm[r, c] and mr[rr, cc]:
                        a.append(fr[rr, cc])
                        b.append(fm[r, c])
            count[i, j] = len(a)
            if len(a) >= 3 and np.std(a) > 0 and np.std(b) > 0:
                out[i, j] = np.corrcoef(a, b)[0, 1]
    return out, count


def test_masked_ncc_equals_the_slow_reference(rng):
    fr, fm = rng.normal(size=(9, 11)), rng.normal(size=(6, 5))
    mr, mm = rng.random((9, 11)) > 0.3, rng.random((6, 5)) > 0.4
    ncc, n = masked_ncc(fr, mr, fm, mm)
    ref, count = slow_masked_ncc(fr, mr, fm, mm)
    assert np.array_equal(n, count)
    assert np.allclose(ncc, ref, atol=1e-9)


def test_masked_ncc_valid_mode_is_the_full_surface_where_the_moving_image_stays_inside(rng):
    fr, fm = rng.normal(size=(12, 14)), rng.normal(size=(6, 5))
    mr, mm = rng.random((12, 14)) > 0.3, rng.random((6, 5)) > 0.4
    ncc, n = masked_ncc(fr, mr, fm, mm, mode="valid")
    ref, count = slow_masked_ncc(fr, mr, fm, mm)
    inside = (slice(6 - 1, 12), slice(5 - 1, 14))  # shifts 0 .. Hr - Hm, 0 .. Wr - Wm
    assert ncc.shape == (12 - 6 + 1, 14 - 5 + 1)
    assert np.array_equal(n, count[inside])
    assert np.allclose(ncc, ref[inside], atol=1e-9)
    assert shift_of_index((2, 3), fm.shape, mode="valid") == (2, 3)


@pytest.mark.parametrize("trial", range(12))
def test_a_trimmed_surface_is_the_full_one_at_every_shift_with_enough_overlap(trial):
    """Shorter transforms (:func:`overlap_trim`) leave out only shifts where less than 30 % of
    the moving support overlaps; every kept shift has the untrimmed values, wrap-around or not,
    on shapes of all proportions and supports crowded to one side."""
    rng = np.random.default_rng(trial)
    hr, wr, hm, wm = rng.integers(4, 40, size=4)
    fr, mr = rng.normal(size=(hr, wr)), rng.random((hr, wr)) < 0.9
    fm, mm = rng.normal(size=(3, hm, wm)), rng.random((3, hm, wm)) < rng.uniform(0.2, 0.9)
    mm[:, : rng.integers(0, hm // 2 + 1)] = False
    mm[1, :, wm // 2 :] = False
    trim = overlap_trim(mm, 0.3)
    ncc, n = masked_ncc(fr, mr, fm, mm)
    ncc_t, n_t = masked_ncc(fr, mr, fm, mm, trim=trim)
    rows, cols = ncc.shape[-2:]
    kept = np.zeros(ncc.shape, bool)
    kept[:, trim[0] : rows - trim[0], trim[1] : cols - trim[1]] = True
    assert np.allclose(ncc_t[kept], ncc[kept], atol=1e-9) and np.array_equal(n_t[kept], n[kept])
    assert not ncc_t[~kept].any() and not n_t[~kept].any()
    counted = n / np.maximum(mm.sum(axis=(-2, -1), keepdims=True), 1) >= 0.3
    assert not (counted & ~kept).any()
    if min(hm, wm) >= 10:
        assert max(trim) > 0  # it does trim


@pytest.mark.parametrize("trial", range(10))
def test_a_reference_with_few_holes_gives_the_same_surfaces_by_its_frame(trial):
    """A reference with data in a rectangle but for a few holes (its corners, say) sums the mask's
    correlations over that frame instead of transforming it: the same counts and NCC as the
    slow reference, full and valid, trimmed or not, for each image of a stack."""
    rng = np.random.default_rng(100 + trial)
    hr, wr = rng.integers(12, 30, size=2)
    hm, wm = rng.integers(3, 11, size=2)
    fr = rng.normal(size=(hr, wr))
    mr = np.zeros((hr, wr), bool)
    r0, c0 = rng.integers(0, 4, size=2)
    mr[r0 : hr - rng.integers(0, 4), c0 : wr - rng.integers(0, 4)] = True
    frame = np.argwhere(mr)
    for q in frame[rng.choice(len(frame), size=rng.integers(0, 4), replace=False)]:
        mr[tuple(q)] = False  # holes, at the frame's edge too
    mr[r0, c0] = False  # a corner
    fm, mm = rng.normal(size=(2, hm, wm)), rng.random((2, hm, wm)) > 0.3
    ref = MaskedReference(fr, mr)
    assert ref.sums_by_frame((hm, wm), (hr + hm, wr + wm))
    trim = overlap_trim(mm, 0.3)
    ncc, n = masked_ncc(ref, None, fm, mm)
    ncc_t, n_t = masked_ncc(ref, None, fm, mm, trim=trim)
    ncc_v, n_v = masked_ncc(ref, None, fm, mm, mode="valid")
    rows, cols = ncc.shape[-2:]
    for k in range(2):
        slow, count = slow_masked_ncc(fr, mr, fm[k], mm[k])
        assert np.array_equal(n[k], count) and np.allclose(ncc[k], slow, atol=1e-9)
        kept = (slice(trim[0], rows - trim[0]), slice(trim[1], cols - trim[1]))
        assert np.array_equal(n_t[k][kept], count[kept])
        assert np.allclose(ncc_t[k][kept], slow[kept], atol=1e-9)
        inside = (slice(hm - 1, hr), slice(wm - 1, wr))
        assert np.array_equal(n_v[k], count[inside])
        assert np.allclose(ncc_v[k], slow[inside], atol=1e-9)


def test_a_reference_with_many_holes_is_transformed(rng):
    ref = MaskedReference(rng.normal(size=(40, 40)), rng.random((40, 40)) > 0.2)
    assert len(ref.holes) > 100
    assert not ref.sums_by_frame((20, 20), (64, 64))


def test_masked_ncc_of_a_stack_is_each_image_alone(rng):
    fr, mr = rng.normal(size=(20, 18)), rng.random((20, 18)) > 0.2
    fm, mm = rng.normal(size=(3, 7, 9)), rng.random((3, 7, 9)) > 0.5
    fm[1] *= 1e3  # a tolerance per image, not one for the stack
    ncc, n = masked_ncc(fr, mr, fm, mm)
    for k in range(3):
        one, n_one = masked_ncc(fr, mr, fm[k], mm[k])
        assert np.array_equal(n[k], n_one)
        assert np.allclose(ncc[k], one, atol=1e-12)


def test_masked_ncc_finds_a_known_shift_under_a_sparse_mask(rng):
    ref = rng.normal(size=(60, 70))
    mov = ref[12:42, 20:45].copy()  # moving pixel (r, c) sits at reference (r + 12, c + 20)
    mask = rng.random(mov.shape) > 0.6  # 40 % of the moving cells known
    ncc, _ = masked_ncc(ref, np.ones_like(ref, bool), np.where(mask, mov, 0), mask)
    peak = np.unravel_index(np.argmax(ncc), ncc.shape)
    assert shift_of_index(peak, mov.shape) == (12, 20)
    assert ncc[peak] == pytest.approx(1.0)


def test_masked_ncc_in_single_precision_agrees_with_double(rng):
    # grids of a sweep's size: a band-passed reference of heights in metres with a hole, and a
    # sparse stack of tie-point grids, 45 % of cells known
    from scipy import ndimage

    field = rng.normal(size=(260, 240)) * 3.0
    fr = field - ndimage.gaussian_filter(field, 6.0)
    mr = np.ones(fr.shape, bool)
    mr[100:140, 30:90] = False
    mm = rng.random((4, 90, 80)) < 0.45
    fm = np.stack([fr[20 + 30 * k : 110 + 30 * k, 40:120] for k in range(4)])
    fm = np.where(mm, fm + rng.normal(scale=0.3, size=fm.shape), 0.0)
    double, n_double = masked_ncc(fr, mr, fm, mm)
    single, n_single = masked_ncc(fr, mr, fm, mm, single=True)
    assert single.dtype == np.float32
    assert np.array_equal(n_single, n_double)
    enough = n_double >= 50  # the sweep scores no fewer common cells
    assert np.abs(single - double)[enough].max() < 1e-4
    for k in range(4):  # and the peak is where the moving grid was cut from
        peak = np.unravel_index(np.argmax(np.where(enough[k], single[k], -1)), single[k].shape)
        assert shift_of_index(peak, mm.shape[1:]) == (20 + 30 * k, 40)


@pytest.mark.parametrize("normalization", ["phase", "pomf", "none"])
def test_cross_power_correlation_finds_a_known_shift(rng, normalization):
    ref = rng.normal(size=(64, 64))
    mov = ref[5:45, 17:57]
    surface = cross_power_correlation(ref, mov, normalization=normalization)
    peak = np.unravel_index(np.argmax(surface), surface.shape)
    assert shift_of_index(peak, mov.shape) == (5, 17)


def test_subpixel_parabola_is_exact_on_a_parabola():
    rr, cc = np.indices((9, 9))
    surface = -((rr - 4.3) ** 2) - 2 * (cc - 3.8) ** 2
    r, c = subpixel_peak(surface, (4, 4))
    assert r == pytest.approx(4.3) and c == pytest.approx(3.8)


def test_subpixel_keeps_the_cell_beside_an_unscored_neighbour():
    rr, cc = np.indices((9, 9))
    surface = -((rr - 4.3) ** 2) - 2 * (cc - 3.8) ** 2
    surface[5, 4] = -np.inf  # no score below the peak: rows stay put, columns still refine
    r, c = subpixel_peak(surface, (4, 4))
    assert r == 4.0 and c == pytest.approx(3.8)


def test_match_score_ranks_as_the_significance_of_the_correlation():
    """Fisher's z of r over n samples, atanh(r) sqrt(n - 3), for blocks of 400 cells: a 50 %
    overlap at r = 0.8 is more significant than a full overlap at r = 0.6, and the score orders
    hypotheses as z does."""
    cells = 400
    cases = [(0.8, 0.5), (0.6, 1.0), (0.3, 1.0), (0.95, 0.3), (0.45, 0.6)]
    z = [np.arctanh(r) * np.sqrt(ov * cells - 3) for r, ov in cases]
    score = [float(match_score(np.array(r), np.array(ov))) for r, ov in cases]
    assert np.argsort(score).tolist() == np.argsort(z).tolist()
    assert score[0] > score[1]  # where the plain r sqrt(overlap) says 0.57 < 0.6
    assert np.isfinite(match_score(np.array(1.0), np.array(1.0)))


def test_local_maxima_are_distinct_and_ordered():
    s = np.zeros((20, 20))
    s[3, 3], s[3, 4], s[15, 10] = 5.0, 4.9, 3.0
    peaks = local_maxima(s, k=2, exclusion=2)
    assert peaks == [(3, 3), (15, 10)]


def test_peak_to_sidelobe_separates_a_sharp_peak_from_noise(rng):
    noise = rng.normal(size=(50, 50))
    sharp = noise.copy()
    sharp[25, 25] = 20.0
    assert peak_to_sidelobe(sharp, (25, 25)) > 15
    assert peak_to_sidelobe(noise, np.unravel_index(np.argmax(noise), noise.shape)) < 5
