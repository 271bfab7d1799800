"""What a sealed patch goes up as (vehicle.patch_form): the packed per-cell votes of today
(CellsForm) or the "sparse/1" form (SparseForm, common/sparse.py: footprint and paint polygons,
key poses, the paint cells' pixel shares). Consumes the mapper's sealed GridPatches and the
optimized poses (world frame) of the frames they were voted from; pure."""

import enum

import numpy as np

from common import sparse
from common.camera import IpmLookup
from common.messages import GridPatch, SparsePatch


class PatchFormKind(enum.Enum):
    CELLS = "cells"
    SPARSE = "sparse"


class CellsForm:
    """GridPatches as they are (codec: packed cells + votes, ~1 byte per cell)."""

    kind = PatchFormKind.CELLS

    def finish(self, patches: list[GridPatch], poses_xyyaw: np.ndarray) -> list[GridPatch]:
        return patches


class SparseForm:
    """GridPatches -> SparsePatches of the same ids (the cells and votes are not kept)."""

    kind = PatchFormKind.SPARSE

    def __init__(self, roi: sparse.Roi):
        self.roi = roi

    def finish(self, patches: list[GridPatch], poses_xyyaw: np.ndarray) -> list[SparsePatch]:
        return [self._sparse(p, poses_xyyaw) for p in patches]

    def _sparse(self, p: GridPatch, poses_xyyaw: np.ndarray) -> SparsePatch:
        geometry = sparse.sparsify(p.cells, p.votes, p.tile, poses_xyyaw, self.roi)
        return SparsePatch(patch_id=p.patch_id, vehicle=p.vehicle, tile=tuple(p.tile),
                           t_first_ns=p.t_first_ns, t_last_ns=p.t_last_ns,
                           traversal=p.traversal, data=sparse.pack(geometry))


def get_patch_form(kind: str, *, ipm: IpmLookup, camera_x_m: float, roi_width_m: float,
                   ipm_stride: int = 1):
    """The configured form; the sparse one takes its Roi from the mapper's IPM lookup."""
    kind = PatchFormKind(kind)
    if kind is PatchFormKind.CELLS:
        return CellsForm()
    return SparseForm(sparse.roi_of_lookup(ipm.ground_xy_m, camera_x_m=camera_x_m,
                                           width_m=roi_width_m, stride=ipm_stride))
