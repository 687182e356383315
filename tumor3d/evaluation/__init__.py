"""Evaluation of the pipeline against reference labels (pure core).

* :mod:`tumor3d.evaluation.metrics` -- Dice, Jaccard, Eq. 9, Table 2
  confusion counts, Bland-Altman, surface distances (HD95, Hausdorff) in mm;
* :mod:`tumor3d.evaluation.emulate` -- thick-slice emulation of thin volumes
  and labels (which thin slices form each thick one);
* :mod:`tumor3d.evaluation.grids` -- world-space overlap and nearest-neighbour
  resampling between voxel grids;
* :mod:`tumor3d.evaluation.registry` -- the registry of evaluations that
  ``tumor3d evaluate`` runs (:func:`register_evaluation`);
* :mod:`tumor3d.evaluation.segmentation` -- the built-in (default) evaluation;
* :mod:`tumor3d.evaluation.geometry` -- the interpolation (Table 4) and
  simplification (Figure 10) evaluations, run when named.

No file I/O here: :mod:`tumor3d.storage.evaluation_io` loads,
:mod:`tumor3d.storage.evaluation_tables` writes, the flow (``flows/evaluate.py``)
wires.
"""

from tumor3d.evaluation.registry import (
    EvaluationCase,
    EvaluationRows,
    register_evaluation,
    registered_evaluations,
    selected_evaluations,
)

__all__ = [
    "EvaluationCase",
    "EvaluationRows",
    "register_evaluation",
    "registered_evaluations",
    "selected_evaluations",
]
