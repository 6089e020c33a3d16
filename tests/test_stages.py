"""The fine stage's part in the verdict (tiereg.stages.fine_stage), on a stand-in fine result."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tiereg import stages
from tiereg.quality import HeightStats
from tiereg.stages import CoarseStage, fine_stage
from tiereg.transform import Transform
from tiereg.verdict import MAX_UNCERTAINTY_NOISE, RefinedPose, Verdict

MOVE = Transform.from_translation((0.4, -0.2, 0.1))


def _start() -> CoarseStage:
    """A confident coarse answer with no verdict to vouch for it (as a translation search)."""
    return CoarseStage(T_local=Transform.identity(), cell_size=10.0,
                       before=HeightStats.from_dz(np.zeros(50), 50), confident=True,
                       confidence=0.9, reasons=())


def _vouched(noise_m: float, scale: float) -> CoarseStage:
    """A confident coarse answer whose verdict measured ``noise_m`` (reference units: the NMAD
    of its smooth-ground height residuals) at a pose of ``scale``."""
    n = 1000
    dz = np.random.default_rng(1).normal(0.0, noise_m, n)
    T = Transform.from_parameters(scale=scale)
    pose = RefinedPose(T, T, True, 0.0, dz, np.linspace(0.0, 100.0, n), np.full(n, 0.1))
    verdict = Verdict(0, (pose,), True, 0.9, (), pose.noise, (float(n),), (np.nan,))
    return CoarseStage(T_local=Transform.identity(), cell_size=10.0,
                       before=HeightStats.from_dz(np.zeros(50), 50), confident=True,
                       confidence=0.9, reasons=(), verdict=verdict)


@pytest.fixture
def fine_result(monkeypatch):
    def use(**fields):
        fields = {"refused": "", "contradicts_coarse": False,
                  "fit": SimpleNamespace(sigma=np.full(7, 0.01), converged=True), **fields}
        result = SimpleNamespace(T_increment=MOVE, method="lsm", seconds=0.0, held=(), **fields)
        monkeypatch.setattr(stages, "register_fine", lambda *a, **k: result)
        return result

    return use


def test_an_accepted_fine_answer_moves_the_pose_and_keeps_the_confidence(fine_result):
    fine_result()
    out = fine_stage(np.zeros((50, 3)), np.ones(50, bool), None, _start(), method="auto",
                     coarse_method="pomf")
    assert out.confident and out.confidence == 0.9
    assert out.T_local.isclose(MOVE)


def test_a_fine_answer_that_contradicts_the_coarse_one_withdraws_the_confidence(fine_result):
    fine_result(refused="it would move the block 3 cells", contradicts_coarse=True)
    out = fine_stage(np.zeros((50, 3)), np.ones(50, bool), None, _start(), method="auto",
                     coarse_method="pomf")
    assert not out.confident
    assert out.confidence <= 0.49  # RESULT.json: at most 0.49 when not confident
    assert out.T_local.isclose(Transform.identity())  # the coarse pose stands
    assert "contradicts the coarse answer" in out.reasons[0]


@pytest.mark.parametrize("converged", [True, False])
def test_the_verdict_vouches_for_a_refused_fine_stage_only_when_it_converged(fine_result,
                                                                              converged):
    refusal = ("it leaves the tie points farther from the lidar surface" if converged
               else "it did not converge in 40 iterations")
    fine_result(refused=refusal, fit=SimpleNamespace(sigma=np.full(7, 0.01),
                                                     converged=converged))
    out = fine_stage(np.zeros((50, 3)), np.ones(50, bool), None, _vouched(0.2, scale=1.0),
                     method="auto", coarse_method="auto")
    assert out.T_local.isclose(Transform.identity())  # the coarse pose stands either way
    assert out.confident == converged
    if converged:
        assert "kept the coarse answer" in out.warnings[0]
    else:
        assert out.confidence <= 0.49 and "could not confirm" in out.reasons[0]


@pytest.mark.parametrize("sigma_xy_m, confident", [(0.25, True), (0.4, False)])
def test_a_fine_answer_less_precise_than_the_noise_allows_is_not_confident(fine_result,
                                                                          sigma_xy_m, confident):
    # noise 0.2 m in reference units, measured at a pose of scale 2 (0.1 in model units): the
    # answer's 1-sigma uncertainty at the block centre, 0.37 or 0.57 m in 3-D, against 2 x 0.2
    start = _vouched(0.2, scale=2.0)
    noise_m = start.verdict.noise * 2.0
    assert noise_m == pytest.approx(0.2, rel=0.1)
    sigma = np.array([1e-4, 1e-4, 1e-4, 1e-4, sigma_xy_m, sigma_xy_m, 0.1])
    fine_result(fit=SimpleNamespace(sigma=sigma, converged=True))
    out = fine_stage(np.zeros((50, 3)), np.ones(50, bool), None, start, method="auto",
                     coarse_method="auto")
    assert out.T_local.isclose(MOVE)  # the answer is kept either way
    uncertainty = np.hypot(np.hypot(sigma_xy_m, sigma_xy_m), 0.1)
    assert (uncertainty <= MAX_UNCERTAINTY_NOISE * noise_m) == confident
    assert out.confident == confident
    if not confident:
        assert out.confidence <= 0.49 and "uncertain by" in out.reasons[0]


def test_held_parameters_do_not_count_as_uncertainty(fine_result):
    sigma = np.array([1e-4, 1e-4, 1e-4, 1e-4, np.nan, np.nan, 0.1])  # x and y held
    fine_result(fit=SimpleNamespace(sigma=sigma, converged=True))
    out = fine_stage(np.zeros((50, 3)), np.ones(50, bool), None, _vouched(0.2, scale=2.0),
                     method="auto", coarse_method="auto")
    assert out.confident
