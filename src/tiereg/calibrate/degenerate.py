"""Which intrinsics a block determines: held, flagged or refined, with the reason.

From the covariance of the refined intrinsics at the adjustment's solution
(:func:`~tiereg.calibrate.adjust.reduced_covariance`), in the units of :class:`Tolerance`:

* an intrinsic whose standard deviation is above its hold limit is not determined: it is put
  back to its input value and held. They are taken one at a time, the worst first, and the
  covariance of the others is conditioned on each one held (a focal length the block does not
  separate from the flying height makes the distortion look undetermined too, until it is held);
* radial distortion terms are held from the lowest up: k2 without k1 would only absorb the
  error of a wrong k1 (seen on a flat nadir block: k1 held at 0, k2 refined to -0.066 against
  0.005, with a small standard deviation);
* between the flag and the hold limit an intrinsic is refined and flagged as weakly determined;
  so is a pair of refined intrinsics correlated beyond :data:`MAX_CORRELATION`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .model import MODELS

log = logging.getLogger(__name__)

# two refined intrinsics correlated beyond this are flagged: the block determines their
# combination, not each one (k1 and k2 are usually correlated by -0.9 to -0.97 and are not)
MAX_CORRELATION = 0.99

Label = tuple[int, int]  # (camera id, index into the camera's params)


@dataclass(frozen=True)
class Tolerance:
    """Standard deviations that decide what the block determines. Above ``hold_*`` an intrinsic
    is not determined (a degenerate geometry): it is held at its input value. Between
    ``flag_*`` and ``hold_*`` it is refined and flagged as weakly determined. Focal length
    relative; principal point in pixels; distortion as the displacement it makes at the image
    corner, in pixels."""

    hold_focal_rel: float = 0.01
    hold_principal_px: float = 5.0
    hold_distortion_px: float = 2.0
    flag_focal_rel: float = 3e-4
    flag_principal_px: float = 0.3
    flag_distortion_px: float = 0.3


TOLERANCE = Tolerance()

_WHY = {"focal": "the block does not separate the focal length from the flying height (level "
                 "ground seen from above)",
        "principal": "the block does not separate the principal point from the camera tilts "
                     "(parallel strips)",
        "distortion": "the block does not separate the distortion from the other intrinsics"}


def kind_of(model_name: str, i: int) -> str:
    """``focal``, ``principal`` or ``distortion``: the kind of parameter ``i`` of a model."""
    return next(n for n, idx in MODELS[model_name].items() if i in idx)


def sigma_shown(rec, label: Label, variance: float) -> float:
    """A standard deviation in the units of :class:`Tolerance`."""
    cid, i = label
    cam = rec.cameras[cid]
    kinds = MODELS[cam.model.name]
    kind = kind_of(cam.model.name, i)
    sigma = math.sqrt(max(variance, 0.0))
    focal = float(np.mean([cam.params[j] for j in kinds["focal"]]))
    if kind == "focal":
        return sigma / abs(float(cam.params[i]))
    if kind == "distortion":
        corner = math.hypot(cam.width / 2, cam.height / 2) / focal
        power = 2 * (kinds["distortion"].index(i) + 1)
        return sigma * focal * corner ** (power + 1)
    return sigma


def _limit(kind: str, tol: Tolerance, pre: str) -> float:
    return getattr(tol, f"{pre}_{kind}_rel" if kind == "focal" else f"{pre}_{kind}_px")


def _reason(kind: str, s: float, limit: float, *, flag: bool) -> str:
    what = {"focal": f"sigma {100 * s:.3f} % > {100 * limit:.3f} %",
            "principal": f"sigma {s:.2f} px > {limit} px",
            "distortion": f"sigma {s:.2f} px at the image corner > {limit} px"}[kind]
    return f"{what}: {_WHY[kind]}; " + ("weakly determined" if flag else
                                        "held at its input value")


def _condition(cov: np.ndarray, k: int) -> np.ndarray:
    """The covariance of the other parameters with parameter ``k`` held (known exactly)."""
    c = cov[:, k]
    return cov - np.outer(c, c) / cov[k, k] if cov[k, k] > 0 else cov


def to_hold(cov: np.ndarray, labels: list[Label], rec, tol: Tolerance = TOLERANCE
            ) -> dict[Label, str]:
    """The refined intrinsics the block does not determine, with the reason (see the module
    docstring: the worst first, the others' covariance conditioned on each one held; radial
    terms above a held one held with it)."""
    cov = np.array(cov, dtype=np.float64)
    active = list(range(len(labels)))
    out: dict[Label, str] = {}
    while active:
        ratio = []
        for k in active:
            kind = kind_of(rec.cameras[labels[k][0]].model.name, labels[k][1])
            s = sigma_shown(rec, labels[k], cov[k, k])
            ratio.append((s / _limit(kind, tol, "hold"), k, kind, s))
        worst, k, kind, s = max(ratio)
        if worst <= 1.0:
            break
        out[labels[k]] = _reason(kind, s, _limit(kind, tol, "hold"), flag=False)
        cov = _condition(cov, k)
        active.remove(k)
    for cid, i in list(out):
        name = rec.cameras[cid].model.name
        terms = MODELS[name]["distortion"]
        if i in terms:
            for j in terms[terms.index(i) + 1:]:
                if (cid, j) in labels and (cid, j) not in out:
                    out[(cid, j)] = ("held with the lower radial term, whose error it would "
                                     "otherwise absorb")
    return out


def weakly_determined(cov: np.ndarray, labels: list[Label], rec, names,
                      tol: Tolerance = TOLERANCE) -> dict[Label, str]:
    """The refined intrinsics the block determines only weakly (standard deviation above the
    flag limit, or correlated with another refined intrinsic beyond :data:`MAX_CORRELATION`),
    with the reason."""
    out: dict[Label, str] = {}
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    for k, label in enumerate(labels):
        kind = kind_of(rec.cameras[label[0]].model.name, label[1])
        s = sigma_shown(rec, label, cov[k, k])
        if s > _limit(kind, tol, "flag"):
            out[label] = _reason(kind, s, _limit(kind, tol, "flag"), flag=True)
        for j, other in enumerate(labels):
            if j == k or other[0] != label[0] or sig[k] == 0 or sig[j] == 0:
                continue
            r = cov[k, j] / (sig[k] * sig[j])
            if abs(r) > MAX_CORRELATION and label not in out:
                other_name = names[rec.cameras[other[0]].model.name][other[1]]
                out[label] = (f"correlated {r:+.3f} with {other_name}: the block determines "
                              "their combination, not each one; weakly determined")
    return out


def at_bound(rec, start: dict[int, np.ndarray], refine_idx: dict[int, tuple[int, ...]],
             bound: float) -> dict[Label, str]:
    """Refined focal lengths that ran to their bound (``bound``, relative): the block does not
    determine them."""
    out = {}
    for cid, cam in rec.cameras.items():
        for i in MODELS[cam.model.name]["focal"]:
            change = abs(cam.params[i] / start[cid][i] - 1)
            if i in refine_idx.get(cid, ()) and change > 0.99 * bound:
                out[(cid, i)] = (f"ran to {100 * bound:.0f} % off its input value: {_WHY['focal']}"
                                 "; held at its input value")
    return out


def hold(rec, start: dict[int, np.ndarray], refine_idx: dict[int, tuple[int, ...]],
         new: dict[Label, str], held: dict[Label, str]) -> None:
    """Put the parameters in ``new`` back to their start value and stop refining them."""
    for (cid, i), reason in new.items():
        log.info("camera %d: holding parameter %d (%s)", cid, i, reason)
        held[(cid, i)] = reason
        refine_idx[cid] = tuple(j for j in refine_idx[cid] if j != i)
        params = np.array(rec.cameras[cid].params)
        params[i] = start[cid][i]
        rec.cameras[cid].params = params
