"""CAD parts of a twin: every splat inherits its face's part (the parts come from the mesh file, see
`reconstruction.mesh_io`); exploded views translate parts away from the assembly centre.

Part labels are what makes a twin editable: the paper's exploded skateboard moves the wheels'
Gaussians off their axles while the deck stays put (section 5).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np

from reconstruction.gaussians import Gaussians
from reconstruction.twin import Twin


def splat_parts(face_index: np.ndarray, face_part: np.ndarray) -> np.ndarray:
    """Part label of each splat [N] from the face it lies on (face_index [N], face_part [F])."""
    return np.asarray(face_part, np.int64)[np.asarray(face_index, np.int64)]


def part_indices(names: Iterable[str | int], part_names: Sequence[str]) -> list[int]:
    """Part names or indices -> indices; an unknown part is a ValueError naming the known ones."""
    out = []
    for p in names:
        if isinstance(p, str) and p in part_names:
            i = list(part_names).index(p)
        elif isinstance(p, (int, np.integer)) or (isinstance(p, str) and p.isdigit()):
            i = int(p)
            if not 0 <= i < len(part_names):
                raise ValueError(f"part index {i} is out of range; the twin has {len(part_names)} parts")
        else:
            raise ValueError(f"no part named {p!r}; the parts are {', '.join(part_names)}")
        out.append(i)
    return out


def part_centroids(means: np.ndarray, part_label: np.ndarray, num_parts: int) -> np.ndarray:
    """Mean splat position of each part [P, 3]; parts without splats get NaN."""
    sums = np.zeros((num_parts, 3))
    np.add.at(sums, part_label, np.asarray(means, np.float64))
    counts = np.bincount(part_label, minlength=num_parts).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts[:, None]


def explode_offsets(centroids: np.ndarray, factor: float, centre: np.ndarray | None = None, moving: np.ndarray | None = None) -> np.ndarray:
    """Per-part translations [P, 3] = factor * (centroid - centre), zero for parts not in `moving` [P] bool.

    `centre` defaults to the mean of the (finite) part centroids, so a part at the centre of the
    assembly (the deck) stays where it is while outer parts (the wheels) slide outwards.
    """
    c = np.asarray(centroids, np.float64)
    finite = np.all(np.isfinite(c), 1)
    centre = c[finite].mean(0) if centre is None else np.asarray(centre, np.float64)
    off = float(factor) * np.where(finite[:, None], c - centre, 0.0)
    if moving is not None:
        off[~np.asarray(moving, bool)] = 0.0
    return off


def explode(means: np.ndarray, part_label: np.ndarray, num_parts: int, factor: float, moving: np.ndarray | None = None) -> np.ndarray:
    """Exploded splat means [N, 3]: each part translated away from the assembly centre by `factor`."""
    off = explode_offsets(part_centroids(means, part_label, num_parts), factor, moving=moving)
    return (np.asarray(means, np.float64) + off[part_label]).astype(np.float32)


def list_parts(twin: Twin) -> list[tuple[int, str, int]]:
    """(index, name, splat count) of each part of `twin`."""
    counts = np.bincount(twin.part_label, minlength=len(twin.part_names))
    return [(i, name, int(counts[i])) for i, name in enumerate(twin.part_names)]


def exploded_splats(
    twin: Twin, factor: float, hidden: Iterable[str | int] = (), moving: Iterable[str | int] | None = None
) -> tuple[Gaussians, np.ndarray]:
    """The twin's Gaussians with its parts exploded by `factor` and the `hidden` parts removed, and the
    part label [M] of each kept one. `moving` limits the explosion to those parts (default: all). Names or indices.
    """
    if not np.isfinite(factor) or factor < 0:
        raise ValueError(f"explode factor must be a finite number >= 0, got {factor}")
    p = len(twin.part_names)
    move_mask = None
    if moving is not None:
        move_mask = np.zeros(p, bool)
        move_mask[part_indices(moving, twin.part_names)] = True
    g = twin.gaussians
    exploded = replace(g, means=explode(g.means, twin.part_label, p, factor, move_mask))
    keep = ~np.isin(twin.part_label, part_indices(hidden, twin.part_names))
    return exploded.subset(keep), twin.part_label[keep]
