"""Gates that refuse a confident wrong twin: masks no object could give, silhouettes every library
model fits alike, a suspiciously perfect fit to a featureless silhouette, and a registration that does
not explain the silhouettes (the part outside its masks).

Each gate returns one sentence per problem; `check_masks` and `check_registration` raise
`QualityError` with the first, so registration and reconstruction stop instead of reporting an
IoU of 1.000 for the wrong part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class QualityError(ValueError):
    """The input or the registration is implausible; the message says which view or model and why."""


@dataclass(frozen=True)
class MaskGate:
    """A mask covering more than `max_cover` or less than `min_cover` of its image is no object's
    silhouette; models whose scores lie within `alike_spread` cannot be told apart; a score above
    `perfect_score` on silhouettes that fill more than `featureless_fill` of their bounding box is
    a rectangle fitting a box, not evidence. A registration whose mean silhouette IoU is below `fit_floor`
    does not explain the masks: the part lies outside them in the views whose IoU is below it."""

    max_cover: float = 0.9
    min_cover: float = 0.0005
    alike_spread: float = 0.02
    perfect_score: float = 0.97
    featureless_fill: float = 0.97
    fit_floor: float = 0.5


def mask_cover(masks: np.ndarray) -> np.ndarray:
    """Fraction of each image [V] a bool mask [V, H, W] (or V masks of their own sizes) covers."""
    return np.array([np.asarray(m, bool).mean() for m in masks])


def bbox_fill(mask: np.ndarray) -> float:
    """Fraction of its bounding box a bool mask [H, W] fills (1.0: a plain rectangle); 0 when empty."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return 0.0
    return float(ys.size / ((ys.max() - ys.min() + 1) * (xs.max() - xs.min() + 1)))


def mask_problems(masks: np.ndarray, gate: MaskGate = MaskGate(), names: list[str] | None = None) -> list[str]:
    """One sentence per view whose mask [V, H, W] covers (nearly) the whole image or none of it."""
    out = []
    for i, c in enumerate(mask_cover(masks)):
        view = names[i] if names else f"view {i}"
        if c > gate.max_cover:
            out.append(
                f"{view}: the mask covers {100 * c:.0f}% of the image, so it is not an object's silhouette "
                "(a wrong mask file or a background difference that changed everywhere)"
            )
        elif c < gate.min_cover:
            out.append(f"{view}: the mask covers none of the image, so the object is not seen")
    return out


def check_masks(masks: np.ndarray, gate: MaskGate = MaskGate(), names: list[str] | None = None) -> None:
    problems = mask_problems(masks, gate, names)
    if problems:
        more = f" ({len(problems) - 1} more view(s) alike)" if len(problems) > 1 else ""
        raise QualityError(f"masks refused: {problems[0]}{more}")


def registration_problems(
    score: float,
    alternatives: list[tuple[str, float]],
    masks: np.ndarray,
    num_models: int,
    model_id: str,
    gate: MaskGate = MaskGate(),
    *,
    per_view_iou: np.ndarray | None = None,
    names: list[str] | None = None,
) -> list[str]:
    """Sentences on a registration (best `score`, the other models' best `alternatives`, its IoU in each view
    `per_view_iou` [V] when known, views named by `names`) that cannot be trusted."""
    out = []
    if per_view_iou is not None and score < gate.fit_floor:
        outside = [names[i] if names else f"view {i}" for i in np.flatnonzero(np.asarray(per_view_iou) < gate.fit_floor)]
        out.append(
            f"'{model_id}' fits these silhouettes with mean IoU {score:.2f}, below the floor {gate.fit_floor:.2f}: the part lies "
            f"outside its mask in {len(outside)} of {len(per_view_iou)} views ({', '.join(outside)})"
        )
    others = [s for _, s in alternatives]
    if num_models >= 3 and len(others) >= 2 and score - min(others) < gate.alike_spread:
        out.append(
            f"every library model fits these silhouettes alike (IoU {score:.3f} for '{model_id}', "
            f"{min(others):.3f} for the worst of {len(others) + 1}), so none can be told apart"
        )
    fills = [bbox_fill(m) for m in np.asarray(masks, bool) if m.any()]
    if score > gate.perfect_score and fills and min(fills) > gate.featureless_fill:
        out.append(
            f"'{model_id}' fits with IoU {score:.3f} silhouettes that are plain rectangles "
            f"(each fills {100 * min(fills):.0f}% or more of its bounding box); any box fits them, so the fit proves nothing"
        )
    return out


def check_registration(
    score: float,
    alternatives: list[tuple[str, float]],
    masks: np.ndarray,
    num_models: int,
    model_id: str,
    gate: MaskGate = MaskGate(),
    *,
    per_view_iou: np.ndarray | None = None,
    names: list[str] | None = None,
) -> None:
    problems = registration_problems(score, alternatives, masks, num_models, model_id, gate, per_view_iou=per_view_iou, names=names)
    if problems:
        raise QualityError(f"registration refused: {problems[0]}")
