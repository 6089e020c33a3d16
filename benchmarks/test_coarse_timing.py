"""Checks of the coarse timing benchmark's re-timing (benchmarks/coarse.py); not part of the main
suite.

    .venv/bin/python -m pytest benchmarks/test_coarse_timing.py
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

import coarse  # noqa: E402


def scripted(monkeypatch, seconds: list[float], stolen: list[float], cores: int = 2) -> list:
    """Runs that take ``seconds`` while the host takes ``stolen`` seconds of CPU time."""
    clock = {"steal": 0.0}
    calls: list[int] = []
    pending = iter(stolen)

    def run_tiereg(method, scene, ref):
        calls.append(len(calls))
        clock["steal"] += next(pending)
        return f"T{len(calls)}", True, seconds[len(calls) - 1], ""

    monkeypatch.setattr(coarse, "run_tiereg", run_tiereg)
    monkeypatch.setattr(coarse, "stolen_seconds", lambda: clock["steal"])
    monkeypatch.setattr(coarse.os, "cpu_count", lambda: cores)
    monkeypatch.setattr(coarse, "loop_ms", lambda number=10: 1.5)
    return calls


def test_a_stolen_run_is_timed_again_and_the_fastest_kept(monkeypatch):
    # shares stolen: 1.2 / (2 x 3.0) = 20 %, 0.4 / (2 x 2.0) = 10 %, then none
    calls = scripted(monkeypatch, [3.0, 2.0, 2.5], [1.2, 0.4, 0.0])
    T, conf, sec, note, stolen, loop, runs = coarse.timed_tiereg("overlap", None, None,
                                                                 retime=True)
    assert (runs, len(calls)) == (3, 3)
    assert (T, sec) == ("T2", 2.0)
    assert stolen == pytest.approx(0.10)
    assert loop == 1.5


def test_a_run_the_host_left_alone_is_timed_once(monkeypatch):
    calls = scripted(monkeypatch, [3.0, 1.0], [0.06, 0.0])  # 1 % stolen: under 5 %
    *_, sec, _, stolen, _, runs = coarse.timed_tiereg("overlap", None, None, retime=True)
    assert (runs, len(calls), sec) == (1, 1, 3.0)
    assert stolen == pytest.approx(0.01)


def test_at_most_retimes_runs(monkeypatch):
    n = coarse.RETIMES
    calls = scripted(monkeypatch, [4.0] * (n + 1), [2.0] * (n + 1))  # 25 % stolen every time
    *_, runs = coarse.timed_tiereg("overlap", None, None, retime=True)
    assert runs == len(calls) == n


def test_without_retiming_one_run_and_no_probe(monkeypatch):
    calls = scripted(monkeypatch, [4.0, 1.0], [2.0, 0.0])
    *_, stolen, loop, runs = coarse.timed_tiereg("overlap", None, None, retime=False)
    assert (runs, len(calls)) == (1, 1)
    assert stolen == pytest.approx(0.25)
    assert math.isnan(loop)


def test_unknown_steal_is_not_retimed(monkeypatch):
    calls = scripted(monkeypatch, [4.0, 1.0], [0.0, 0.0])
    monkeypatch.setattr(coarse, "stolen_seconds", lambda: float("nan"))
    *_, stolen, _, runs = coarse.timed_tiereg("overlap", None, None, retime=True)
    assert (runs, len(calls)) == (1, 1)
    assert math.isnan(stolen)
