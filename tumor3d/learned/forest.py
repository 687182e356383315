"""A gradient-boosted tree ensemble as flat arrays: inference in numba, no pickle.

A trained LightGBM binary model (``Booster.dump_model()``, its documented
JSON) is flattened into five arrays (:func:`forest_from_lightgbm_dump`):
per node its split feature (``-1`` at a leaf), threshold, children and leaf
value. :func:`predict_logit` walks every tree for every row (``x <= t``
goes left, LightGBM's ``decision_type`` ``"<="``) and sums the leaves;
:func:`predict_proba` applies the logistic function. The model is stored as
an ``.npz`` of plain arrays plus its JSON metadata (:meth:`ForestModel.to_bytes`,
read back with ``allow_pickle=False``), so loading a model runs no code.
Inference needs numpy and numba only; LightGBM is needed for training.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, field, replace
from typing import Any

import numba
import numpy as np

from tumor3d.errors import InputError
from tumor3d.learned.archive import UNREADABLE, archive_error, check_archive

# The prediction runs on numba's parallel layer, OpenMP first: numba tries TBB
# first and prints a warning when the TBB already loaded in the process is too
# old (Open3D, which the render stage imports, ships one), then falls back; OpenMP
# (libgomp) is thread-safe, as a cohort's parallel lanes need. A user's own
# NUMBA_THREADING_LAYER or NUMBA_THREADING_LAYER_PRIORITY is left alone.
if not os.environ.get("NUMBA_THREADING_LAYER_PRIORITY") and (
    os.environ.get("NUMBA_THREADING_LAYER", "default") == "default"
):
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

__all__ = ["ForestModel", "forest_from_lightgbm_dump", "predict_logit", "predict_proba"]

_ARRAYS = ("feature", "threshold", "left", "right", "value", "roots")


@dataclass(frozen=True)
class ForestModel:
    """A binary tree ensemble: ``logit(x) = sum over trees of the leaf x reaches``.

    Attributes
    ----------
    feature : (n_nodes,) int32
        Split feature of each node; ``-1`` at a leaf.
    threshold : (n_nodes,) float64
        ``x[feature] <= threshold`` goes to ``left``.
    left, right : (n_nodes,) int32
        Children (global node indices; ``-1`` at a leaf).
    value : (n_nodes,) float64
        Leaf value (0 at internal nodes).
    roots : (n_trees,) int32
        Root node of each tree.
    meta : dict
        JSON-able description: ``feature_names``, ``threshold`` (probability
        cut), training cases, scores, ... (see ``reports/model_card.md``).
    context : ForestModel or None
        An auto-context second stage (:mod:`tumor3d.learned.context`): a
        forest on the features plus the context features of this forest's
        probability, whose probability is the model's answer. None = one stage.
    file_sha256 : str
        SHA-256 of the bytes it was read from (:meth:`from_bytes`; ``sha256sum`` of the
        ``.npz``, as ``tumor3d train`` records it in ``training.json``), "" when built
        in memory. Not part of :meth:`digest` or equality.
    """

    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    value: np.ndarray
    roots: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    context: ForestModel | None = None
    file_sha256: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.context is not None:
            if not isinstance(self.context, ForestModel):
                raise InputError("a forest's context stage must be a ForestModel")
            if self.context.context is not None:
                raise InputError("a forest has at most two stages")
        n = self.feature.shape[0]
        for name in ("threshold", "left", "right", "value"):
            if getattr(self, name).shape != (n,):
                raise InputError(f"forest array {name!r} must have shape ({n},)")
        if self.roots.ndim != 1 or self.roots.size == 0:
            raise InputError("a forest needs at least one tree")
        internal = self.feature >= 0
        for name in ("left", "right"):
            child = getattr(self, name)[internal]
            if child.size and (child.min() < 0 or child.max() >= n):
                raise InputError(f"forest array {name!r} points outside the node table")
        if self.roots.min() < 0 or self.roots.max() >= n:
            raise InputError("forest roots point outside the node table")
        # each tree stored root first (forest_from_lightgbm_dump): a child after its node,
        # so that every walk ends (a loop would never return, nor heed a signal)
        nodes = np.flatnonzero(internal)
        backwards = (self.left[nodes] <= nodes) | (self.right[nodes] <= nodes)
        if backwards.any():
            raise InputError("forest trees must list each child after its node (no loops)")

    @property
    def n_features(self) -> int:
        """Number of input columns the trees read (``len(meta['feature_names'])`` if given)."""
        names = self.meta.get("feature_names")
        if names:
            return len(names)
        return int(self.feature.max(initial=-1)) + 1

    def to_bytes(self) -> bytes:
        """The model as ``.npz`` bytes: the arrays and ``meta`` as JSON (no pickle).

        A second stage's arrays and metadata are stored beside, prefixed ``context_``.
        """
        buf = io.BytesIO()
        arrays = {k: getattr(self, k) for k in _ARRAYS}
        arrays["meta"] = _json_bytes(self.meta)
        if self.context is not None:
            arrays.update({_CTX + k: getattr(self.context, k) for k in _ARRAYS})
            arrays[_CTX + "meta"] = _json_bytes(self.context.meta)
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, *, source: str = "model") -> ForestModel:
        """Read :meth:`to_bytes`; never unpickles. ``source`` names it in errors."""
        check_archive(data, source=source)
        try:
            loaded = np.load(io.BytesIO(data), allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):  # one .npy array
                raise ValueError("a single array, not an .npz archive of a model's arrays")
            with loaded as z:
                stages = [""] + ([_CTX] if _CTX + "feature" in z.files else [])
                read = [
                    (
                        {k: np.array(z[pre + k]) for k in _ARRAYS},
                        json.loads(bytes(z[pre + "meta"]).decode()),
                    )
                    for pre in stages
                ]
        except UNREADABLE as exc:
            raise InputError(
                f"{source}: not a readable tumor3d forest model ({archive_error(exc)})"
            ) from None
        context = None
        for arrays, meta in reversed(read):
            try:  # the arrays' checks (shapes, indices, no loops), naming the file
                if not isinstance(meta, dict):
                    raise InputError("its metadata is not a JSON object")
                context = cls(
                    arrays["feature"].astype(np.int32),
                    arrays["threshold"].astype(np.float64),
                    arrays["left"].astype(np.int32),
                    arrays["right"].astype(np.int32),
                    arrays["value"].astype(np.float64),
                    arrays["roots"].astype(np.int32),
                    meta,
                    context,
                )
            except (InputError, ValueError, IndexError, TypeError) as exc:
                raise InputError(f"{source}: not a valid tumor3d forest model ({exc})") from None
        assert context is not None
        return replace(context, file_sha256=hashlib.sha256(data).hexdigest())

    def digest(self) -> str:
        """SHA-256 of the arrays and metadata (independent of the compression)."""
        h = hashlib.sha256()
        for k in _ARRAYS:
            a = np.ascontiguousarray(getattr(self, k))
            h.update(k.encode() + str(a.dtype).encode() + a.tobytes())
        h.update(json.dumps(self.meta, sort_keys=True).encode())
        if self.context is not None:
            h.update(b"context" + self.context.digest().encode())
        return h.hexdigest()


#: Prefix of the second stage's arrays in the ``.npz``.
_CTX = "context_"


def _json_bytes(meta: dict[str, Any]) -> np.ndarray:
    return np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)


def forest_from_lightgbm_dump(
    dump: dict[str, Any], meta: dict[str, Any] | None = None
) -> ForestModel:
    """Flatten ``lightgbm.Booster.dump_model()`` (a binary model with numeric splits).

    Raises
    ------
    InputError
        For a categorical split or a decision type other than ``"<="``, or
        a missing-value rule that sends NaN somewhere other than where a
        finite feature would go (the features here are always finite).
    """
    feature: list[int] = []
    threshold: list[float] = []
    left: list[int] = []
    right: list[int] = []
    value: list[float] = []
    roots: list[int] = []

    def add(node: dict[str, Any]) -> int:
        i = len(feature)
        feature.append(-1)
        threshold.append(0.0)
        left.append(-1)
        right.append(-1)
        value.append(0.0)
        if "leaf_value" in node and "split_feature" not in node:
            value[i] = float(node["leaf_value"])
            return i
        if node.get("decision_type", "<=") != "<=":
            raise InputError(f"unsupported decision type {node.get('decision_type')!r}")
        feature[i] = int(node["split_feature"])
        threshold[i] = float(node["threshold"])
        li = add(node["left_child"])
        ri = add(node["right_child"])
        left[i], right[i] = li, ri
        return i

    for tree in dump["tree_info"]:
        roots.append(add(tree["tree_structure"]))
    info = dict(meta or {})
    if "feature_names" not in info and "feature_names" in dump:
        info["feature_names"] = list(dump["feature_names"])
    return ForestModel(
        np.asarray(feature, np.int32),
        np.asarray(threshold, np.float64),
        np.asarray(left, np.int32),
        np.asarray(right, np.int32),
        np.asarray(value, np.float64),
        np.asarray(roots, np.int32),
        info,
    )


#: Rows per block of :func:`_walk` (a thread's unit; the block's rows stay in cache while
#: every tree is walked for them, each tree's nodes while the block passes it).
_BLOCK_ROWS = 1024


@numba.njit(parallel=True, cache=True, nogil=True)
def _walk(x, feature, threshold, left, right, value, roots):  # pragma: no cover - numba
    """The summed leaf values of every row: blocks of rows in parallel, tree after tree.

    Four rows go down a tree together (their branches are independent, so one
    row's unpredictable branch does not stall the other three); each row's
    leaves are summed in tree order, so the sum is the naive walk's, bit for bit.
    """
    n = x.shape[0]
    out = np.zeros(n, np.float64)
    for b in numba.prange((n + _BLOCK_ROWS - 1) // _BLOCK_ROWS):
        lo = b * _BLOCK_ROWS
        hi = min(n, lo + _BLOCK_ROWS)
        for t in range(roots.shape[0]):
            root = roots[t]
            i = lo
            while i + 4 <= hi:
                n0 = root
                n1 = root
                n2 = root
                n3 = root
                moving = True
                while moving:
                    moving = False
                    if feature[n0] >= 0:
                        n0 = left[n0] if x[i, feature[n0]] <= threshold[n0] else right[n0]
                        moving = True
                    if feature[n1] >= 0:
                        n1 = left[n1] if x[i + 1, feature[n1]] <= threshold[n1] else right[n1]
                        moving = True
                    if feature[n2] >= 0:
                        n2 = left[n2] if x[i + 2, feature[n2]] <= threshold[n2] else right[n2]
                        moving = True
                    if feature[n3] >= 0:
                        n3 = left[n3] if x[i + 3, feature[n3]] <= threshold[n3] else right[n3]
                        moving = True
                out[i] += value[n0]
                out[i + 1] += value[n1]
                out[i + 2] += value[n2]
                out[i + 3] += value[n3]
                i += 4
            while i < hi:
                node = root
                while feature[node] >= 0:
                    node = left[node] if x[i, feature[node]] <= threshold[node] else right[node]
                out[i] += value[node]
                i += 1
    return out


def float32_at_most(threshold: np.ndarray) -> np.ndarray:
    """The largest float32 at most each threshold, so the walk compares in float32.

    ``x <= t`` holds for a float32 ``x`` exactly when ``x <= float32_at_most(t)`` does.

    >>> t = np.array([0.1, 0.5, -0.1])
    >>> t32 = float32_at_most(t)
    >>> bool(np.all(t32 <= t)), bool(np.float32(0.1) <= t[0]), bool(np.float32(0.1) <= t32[0])
    (True, False, False)
    >>> float(t32[1]) == 0.5
    True
    """
    t = np.asarray(threshold, np.float64)
    with np.errstate(over="ignore"):
        t32 = t.astype(np.float32)
    above = t32.astype(np.float64) > t
    t32[above] = np.nextafter(t32[above], np.float32(-np.inf))
    return t32


def predict_logit(model: ForestModel, x: np.ndarray) -> np.ndarray:
    """The summed leaf values (log-odds) of every row of ``x``.

    Parameters
    ----------
    model : ForestModel
    x : (n, n_features) ndarray of float
        Finite feature rows.

    Returns
    -------
    (n,) ndarray of float64

    Examples
    --------
    >>> stump = ForestModel(np.array([0, -1, -1], np.int32), np.array([0.5, 0, 0]),
    ...                     np.array([1, -1, -1], np.int32), np.array([2, -1, -1], np.int32),
    ...                     np.array([0, -1.0, 2.0]), np.array([0], np.int32))
    >>> predict_logit(stump, np.array([[0.0], [1.0]])).tolist()
    [-1.0, 2.0]
    """
    if not isinstance(model, ForestModel):
        raise InputError(f"model must be a ForestModel, got {type(model).__name__}")
    arr = np.asarray(x, dtype=np.float32)
    if arr.ndim != 2:
        raise InputError(f"x must be 2-D (rows, features), got shape {arr.shape}")
    if arr.shape[1] < int(model.feature.max(initial=-1)) + 1:
        raise InputError(
            f"x has {arr.shape[1]} features but the model reads feature {int(model.feature.max())}"
        )
    if arr.shape[0] == 0:
        return np.zeros(0, np.float64)
    return _walk(
        np.ascontiguousarray(arr),
        model.feature,
        float32_at_most(model.threshold),
        model.left,
        model.right,
        model.value,
        model.roots,
    )


def predict_proba(model: ForestModel, x: np.ndarray) -> np.ndarray:
    """Probability of the positive class, ``1 / (1 + exp(-logit))``."""
    z = predict_logit(model, x)
    return 1.0 / (1.0 + np.exp(-np.clip(z, -50.0, 50.0)))
