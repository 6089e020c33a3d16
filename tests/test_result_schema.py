"""RESULT.json against its contract (docs/result-json.md): every field the contract names is
written, and every field written is named there, for the coarse stage's typed evidence too."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from scenes import make_scene

from tiereg import Transform
from tiereg.pipeline import register

DOC = Path(__file__).resolve().parents[1] / "docs" / "result-json.md"
# written only by some methods or in some cases (the contract says when)
SOMETIMES = {"coarse": {"other_channel", "decided_by", "model_check", "moving_occupancy",
                        "heading_from_moments_deg", "anisotropy_moving",
                        "anisotropy_reference"},
             "fine": {"note"}}


def documented(section: str) -> list[set[str]]:
    """The backticked names in the first column of each table under ``section``'s heading."""
    text = DOC.read_text()
    start = text.index(section)
    end = text.find("\n#", start + len(section))
    tables: list[set[str]] = []
    for line in text[start:end if end > 0 else None].splitlines():
        if line.startswith("| field"):
            tables.append(set())
        elif line.startswith("| `"):
            tables[-1] |= set(re.findall(r"`([a-z_A-Z0-9]+)`", line.split("|")[1]))
    return tables


@pytest.fixture(scope="module")
def result_json() -> dict:
    scene = make_scene(seed=0, T_mov_ref=Transform.from_parameters(scale=1.3, kappa=0.4),
                       lidar_points=200_000)
    result = register(scene.tie_mov, scene.lidar, coarse="auto")
    return json.loads(result.to_json())


@pytest.mark.parametrize("section", ["## The transform", "## The verdict", "## Sizes and times"])
def test_the_top_level_fields_are_the_documented_ones(result_json, section):
    missing = set().union(*documented(section)) - set(result_json)
    assert not missing, f"{section}: documented but not written: {sorted(missing)}"


@pytest.mark.parametrize("stage", ["coarse", "verdict", "fine"])
def test_each_stage_writes_what_the_contract_names_and_nothing_else(result_json, stage):
    written = next(s for s in result_json["stages"] if s["name"] == stage)
    names = documented(f"### `{stage}`")[0]
    missing = names - set(written) - SOMETIMES.get(stage, set())
    assert not missing, f"{stage}: documented but not written: {sorted(missing)}"
    extra = set(written) - names - {"name"}
    assert not extra, f"{stage}: written but not documented: {sorted(extra)}"


def test_each_pose_of_the_verdict_is_written_as_documented(result_json):
    verdict = next(s for s in result_json["stages"] if s["name"] == "verdict")
    names = documented("### `verdict`")[1]
    assert len(verdict["poses"]) >= 2  # the answer and at least one rival
    for pose in verdict["poses"]:
        assert set(pose) == names


def test_the_coarse_evidence_is_typed_and_written_from_its_types(result_json):
    """The typed evidence and the file agree: the search's best peak, the refinement."""
    scene = make_scene(seed=0, T_mov_ref=Transform.from_parameters(scale=1.3, kappa=0.4),
                       lidar_points=200_000)
    coarse = register(scene.tie_mov, scene.lidar, coarse="auto", fine="none").coarse
    ev = coarse.evidence
    written = next(s for s in result_json["stages"] if s["name"] == "coarse")
    assert ev.channel == written["channel"] and ev.decided_by == written["decided_by"]
    assert ev.refinement is not None and ev.refinement.converged
    assert written["refinement"]["converged"] is True
    assert written["search_best"]["scale"] == pytest.approx(ev.search_best.scale)
    # the moving frame was turned by 0.4 rad and scaled by 1.3 from the reference's
    assert ev.search_best.kappa_deg % 360 == pytest.approx(360 - 22.918, abs=8.0)
    assert 1 / ev.search_best.scale == pytest.approx(1.3, rel=0.15)


@pytest.mark.parametrize("method", ["pomf", "moments"])
def test_the_other_coarse_methods_write_only_documented_fields(method):
    scene = make_scene(seed=0, lidar_points=200_000)
    result = json.loads(register(scene.tie_mov, scene.lidar, coarse=method,
                                 fine="none").to_json())
    written = next(s for s in result["stages"] if s["name"] == "coarse")
    extra = set(written) - documented("### `coarse`")[0] - {"name"}
    assert not extra, f"{method}: written but not documented: {sorted(extra)}"
    own = {"pomf": "model_check", "moments": "heading_from_moments_deg"}[method]
    assert own in written
