"""The fine stage's part in the verdict (tiereg.stages.fine_stage), on a stand-in fine result."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tiereg import stages
from tiereg.quality import HeightStats
from tiereg.stages import CoarseStage, fine_stage
from tiereg.transform import Transform

MOVE = Transform.from_translation((0.4, -0.2, 0.1))


def _start() -> CoarseStage:
    """A confident coarse answer with no verdict to vouch for it (as a translation search)."""
    return CoarseStage(T_local=Transform.identity(), cell_size=10.0,
                       before=HeightStats.from_dz(np.zeros(50), 50), confident=True,
                       confidence=0.9, reasons=())


@pytest.fixture
def fine_result(monkeypatch):
    def use(**fields):
        fields = {"refused": "", "contradicts_coarse": False, **fields}
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
