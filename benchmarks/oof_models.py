"""Out-of-fold models for the real-data benchmarks: the learned models that never saw a case.

The shipped models (``tumor3d/learned/models``) were trained on every labelled case of
``../shared/data``, so a benchmark that runs them on those cases (``real_segmentation.py``,
``real_robustness.py``, ``pseudo_healthy.py``, ``transplant.py``) scores them on their own
training patients. With ``--oof-models DIR`` (and ``--cnn-folds``) such a benchmark runs each
case with the models of the cross-validation fold that held its patient out, as
``learned_cv.py`` scores it:

- ``DIR``: ``learned_cv.py --method learned ... --save-models DIR`` (the fold forests
  ``<family>_fold<k>.npz`` and ``folds.json``: each patient's fold, each image file's patient);
- ``--cnn-folds``: the fold U-Nets of ``cnn_cv.py`` (``unet_fold<k>.npz``, the same folds),
  one folder per training seed, averaged as the shipped ensemble is; required where the
  default averages a U-Net in (FLAIR), and a net that records its fold must record ``k``.
  (``cnn_cv.py`` deals the folds on every case; ``learned_cv.py --limit-lgg`` or another
  ``--folds`` would deal them otherwise: use the same cases and folds for both.)

The models are read as the pipeline reads its own (``ForestModel.from_bytes``,
``unet_from_bytes``); the U-Net is used on the sequences that ship one
(:data:`tumor3d.learned.shipped.CNN_MODELS`) when ``segment.learned_cnn`` is ``auto``.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

from tumor3d.learned.cnn import unet_from_bytes
from tumor3d.learned.forest import ForestModel
from tumor3d.learned.shipped import CNN_MODELS, check_family, model_family


class OutOfFold:
    """Fold models by image file: :meth:`models` gives ``segment_tumor``'s ``model``/``cnn``."""

    def __init__(self, models_dir: str | Path, cnn_dirs: list[str] | None = None) -> None:
        self.dir = Path(models_dir)
        table = json.loads((self.dir / "folds.json").read_text())
        self.folds: dict[str, int] = table["folds"]
        self.images: dict[str, str] = table["images"]
        self.cnn_dirs = [Path(d) for d in cnn_dirs or ()]

    def patient(self, image: str | Path) -> str:
        """The patient of the image file ``image`` (as ``learned_cv.py`` names it)."""
        key = str(Path(image).resolve())
        if key not in self.images:
            raise KeyError(f"{image}: not a case of the cross-validation ({self.dir}/folds.json)")
        return self.images[key]

    def fold(self, image: str | Path) -> int:
        return int(self.folds[self.patient(image)])

    def models(self, image: str | Path, modality: str, learned_cnn: str = "auto") -> dict[str, Any]:
        """``{"model": ..., "cnn": ...}`` of the fold that held ``image``'s patient out."""
        k = self.fold(image)
        family = model_family(modality)
        model = _forest(self.dir / f"{family}_fold{k}.npz")
        check_family(model, family, str(self.dir / f"{family}_fold{k}.npz"))
        if self.patient(image) not in model.meta.get("held_out_patients", ()):
            raise ValueError(f"{image}: fold {k}'s forest lists other held-out patients")
        cnn = None
        if learned_cnn == "auto" and modality.lower() in CNN_MODELS:
            if not self.cnn_dirs:  # the forest alone would be scored as the default
                raise ValueError(
                    f"{image}: {modality} runs the forest + U-Net mean: give the fold U-Nets "
                    "(--cnn-folds), or segment.learned_cnn: off for the forest alone"
                )
            cnn = tuple(_net(d / f"unet_fold{k}.npz") for d in self.cnn_dirs)
            for d, net in zip(self.cnn_dirs, cnn, strict=True):
                # cnn_cv.py records its fold (nets written before it did record none):
                # a net of another fold saw this patient
                if net.meta.get("fold", k) != k:
                    raise ValueError(
                        f"{d / f'unet_fold{k}.npz'}: trained as fold {net.meta.get('fold')}, "
                        f"not {k}"
                    )
        return {"model": model, "cnn": cnn}


@cache
def _forest(path: Path) -> ForestModel:
    return ForestModel.from_bytes(path.read_bytes(), source=str(path))


@cache
def _net(path: Path):
    return unet_from_bytes(path.read_bytes(), source=str(path))
