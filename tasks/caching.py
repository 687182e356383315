"""Cache keys of the pipeline stages: derived here and nowhere else.

A stage's key is the SHA-256 of the canonical JSON of

* the stage name (``preprocess``, ``segment-tumor``, ...);
* a digest of the stage's code: the source text of the core modules it
  calls and of the task module itself, plus :data:`STORE_FORMAT_VERSION`;
* the stage's inputs: artifact references contribute their content digest
  only (which covers dtype, shape, spacing and affine), pydantic configs
  their canonical JSON, plain values themselves. Inputs listed in
  :data:`IGNORED_INPUTS` (the store location) do not count.

The flow run id is *not* part of the key, so a result computed by any earlier
run is reused. Prefect's default policy would key on the run id and its
``TASK_SOURCE`` ignores the core functions a task calls; see
``prefect/cache_policies.py``.
"""

from __future__ import annotations

import hashlib
import importlib.util
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from prefect.cache_policies import CachePolicy
from pydantic import BaseModel

from storage.store import ArtifactRef, canonical_dumps

__all__ = [
    "IGNORED_INPUTS",
    "STORE_FORMAT_VERSION",
    "StageCachePolicy",
    "code_digest",
    "fingerprint",
    "stage_cache_key",
]

#: Bump when the on-disk form of artifacts changes incompatibly.
STORE_FORMAT_VERSION = "1"

#: Task parameters that locate things but do not change the result.
IGNORED_INPUTS = frozenset({"store_root"})


@cache
def code_digest(modules: tuple[str, ...]) -> str:
    """SHA-256 of the source files of ``modules`` (dotted names), in order.

    Parameters
    ----------
    modules : tuple of str
        Importable module names, e.g. ``("tumor3d.segment", "tasks.stages")``.
    """
    h = hashlib.sha256(f"format={STORE_FORMAT_VERSION}\0".encode())
    for name in modules:
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            raise ValueError(f"cannot locate the source of module {name!r}")
        h.update(name.encode() + b"\0")
        h.update(Path(spec.origin).read_bytes())
    return h.hexdigest()


def fingerprint(value: Any) -> Any:
    """The JSON-able identity of a task input, as it enters a cache key.

    Artifact references are reduced to their content digest; pydantic models
    to their JSON dump (``ArtifactRef`` fields nested in them included);
    mappings and sequences recursively. A model may list fields that do not
    identify its content (such as a file location) in a ``__cache_exclude__``
    class attribute.
    """
    if isinstance(value, ArtifactRef):
        return {"artifact": value.digest}
    if isinstance(value, BaseModel):
        excluded = getattr(type(value), "__cache_exclude__", frozenset())
        return {
            "model": type(value).__name__,
            "fields": {
                k: fingerprint(getattr(value, k))
                for k in type(value).model_fields
                if k not in excluded
            },
        }
    if isinstance(value, dict):
        return {str(k): fingerprint(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, list | tuple):
        return [fingerprint(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise TypeError(f"cannot fingerprint a task input of type {type(value).__name__}")


def stage_cache_key(stage: str, modules: tuple[str, ...], inputs: dict[str, Any]) -> str:
    """The cache key of one stage run (see the module docstring)."""
    document = {
        "stage": stage,
        "code": code_digest(modules),
        "inputs": {k: fingerprint(v) for k, v in sorted(inputs.items()) if k not in IGNORED_INPUTS},
    }
    return f"{stage}-{hashlib.sha256(canonical_dumps(document).encode()).hexdigest()}"


@dataclass
class StageCachePolicy(CachePolicy):
    """Prefect cache policy that delegates to :func:`stage_cache_key`."""

    stage: str = ""
    modules: tuple[str, ...] = field(default_factory=tuple)

    def compute_key(
        self,
        task_ctx: Any,
        inputs: dict[str, Any],
        flow_parameters: dict[str, Any],
        **kwargs: Any,
    ) -> str | None:
        """Return the stage's content-derived key."""
        return stage_cache_key(self.stage, self.modules, inputs)
