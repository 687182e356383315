"""Cache keys of the pipeline stages: derived here and nowhere else.

A stage's key is built from three small, composable cache policies in the
style of ``prefect/cache_policies.py`` (combined with ``+`` into Prefect's
``CompoundCachePolicy``):

* :class:`StageCode` -- the stage name, :data:`ARTIFACT_FORMAT_VERSION` and
  the syntax tree, docstrings removed, of every project module the stage's
  adapter imports, directly or transitively (:func:`module_closure`, an AST
  walk over ``tumor3d/``, ``storage/`` and ``tasks/``, computed once per
  process; :func:`syntax_dump`: a comment, a docstring or a blank line
  changes no key, a constant or an operator does), with the bytes of the
  data files those modules read (:data:`DATA_FILES`) and the installed
  versions of the numerical packages (numpy, scipy, scikit-image, numba, ...:
  :data:`tumor3d.storage.versions.NUMERICAL_PACKAGES`) those modules import
  (:func:`package_versions`, read from :func:`tumor3d.storage.versions.versions`,
  the function provenance and the publish key read);
* :class:`StageConfig` -- the canonical JSON of the stage's configuration
  (the ``config`` parameter, a pydantic model);
* :class:`InputArtifacts` -- every other input: artifact references by their
  content digest only (which covers dtype, shape, spacing and affine),
  pydantic models by their fields (less those a model lists in
  ``__cache_exclude__``: the user input's location and patient id, see
  :class:`tumor3d.tasks.spec.InputSource`), plain values as they are. Parameters in
  :data:`IGNORED_INPUTS` (the store location) do not count.

No key holds a patient id (issue 29): the same file under two ids is one
computation, and no cached output carries an id (the scan artifact does not
store it); the flow names the patient when it publishes.

The flow run id is *not* part of the key, so a result computed by any earlier
run is reused; Prefect's default policy would key on the run id, and its
``TASK_SOURCE`` ignores the core functions a task calls.

The code of the artifact store's own codecs and back-ends
(``storage/store.py`` with ``refs.py`` and ``atomic.py``, ``storage/formats.py``,
``storage/objectstore.py``: :data:`FORMAT_MODULES`) are not hashed: the on-disk
form of artifacts is covered by :data:`ARTIFACT_FORMAT_VERSION`, bumped by
hand when it changes. The modules they import are walked and hashed as any
other (``storage/nifti.py``, ``tumor3d/imaging/scan.py``, ...). The syntax tree's
form is Python's (``ast.dump``): another Python version may give other keys.
"""

from __future__ import annotations

import ast
import hashlib
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache, wraps
from pathlib import Path
from typing import Any

from prefect.cache_policies import CachePolicy
from pydantic import BaseModel

from tumor3d.package_layout import PROJECT_ROOT, module_path
from tumor3d.storage.store import ArtifactRef, canonical_dumps
from tumor3d.storage.versions import NUMERICAL_PACKAGES, versions

__all__ = [
    "ARTIFACT_FORMAT_VERSION",
    "DATA_FILES",
    "FORMAT_MODULES",
    "IGNORED_INPUTS",
    "PROJECT_PACKAGES",
    "PROJECT_ROOT",
    "InputArtifacts",
    "StageCode",
    "StageConfig",
    "closure_packages",
    "code_digest",
    "fingerprint",
    "module_closure",
    "package_versions",
    "stage_cache_policy",
    "syntax_dump",
]

#: Bump when the on-disk form of any artifact (NIfTI/PLY/parquet/PNG/JSON
#: encoding, metadata layout, digest rule) changes incompatibly.
#: 2: a scan artifact's metadata no longer holds the patient id (issue 29).
ARTIFACT_FORMAT_VERSION = "2"

#: Task parameters that locate things but do not change the result.
IGNORED_INPUTS = frozenset({"store_root"})

#: Top-level packages whose modules enter code digests (the one namespace).
PROJECT_PACKAGES = ("tumor3d",)

#: The store's codecs: covered by :data:`ARTIFACT_FORMAT_VERSION`, their source not hashed.
FORMAT_MODULES = frozenset(
    {
        "tumor3d.storage.store",
        "tumor3d.storage.refs",
        "tumor3d.storage.atomic",
        "tumor3d.storage.formats",
        "tumor3d.storage.objectstore",
    }
)

#: Data files a module reads as part of its behaviour (paths relative to the project
#: root): when the module is in a stage's closure, their bytes enter its code digest.
#: The shipped learned models: a retrained model recomputes the segment stage.
DATA_FILES: dict[str, tuple[str, ...]] = {
    "tumor3d.learned.shipped": (
        "tumor3d/learned/models/hyper.npz",
        "tumor3d/learned/models/t1c.npz",
        "tumor3d/learned/models/unet_flair_seed0.npz",
        "tumor3d/learned/models/unet_flair_seed1.npz",
    ),
}


def _module_file(name: str, root: Path) -> Path | None:
    """The source file of project module ``name`` under ``root``, if any.

    ``root`` (default :data:`PROJECT_ROOT`, the folder holding ``tumor3d/``) holds the
    packages as :func:`tumor3d.package_layout.module_path` lays them out:
    ``tumor3d.tasks.caching`` is ``tasks/caching.py`` in the repository.
    """
    base = root / module_path(name)
    if (base / "__init__.py").is_file():
        return base / "__init__.py"
    if base.with_suffix(".py").is_file():
        return base.with_suffix(".py")
    return None


def _with_parents(name: str) -> list[str]:
    """``a.b.c`` -> ``[a, a.b, a.b.c]``: importing a module runs its packages."""
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def _syntax_digest_of(name: str, path: Path, root: Path) -> str:
    """SHA-256 of one module's syntax tree without docstrings (:func:`syntax_dump`)."""
    return _parse_module(name, str(path), str(root), path.read_bytes()).syntax_sha256


#: ``ast.parse`` is not thread-safe on CPython 3.11 (the AST constructor's recursion
#: depth is shared state: ``SystemError: AST constructor recursion depth mismatch``,
#: python/cpython#106905), and a cohort's lanes compute code digests concurrently.
_AST_LOCK = threading.Lock()

#: One lock for the per-process digests (:func:`module_closure`, :func:`code_digest`,
#: :func:`closure_packages`): a cohort's lanes and task threads ask for them at once.
_DIGEST_LOCK = threading.RLock()


def _once_per_process(fn: Callable[..., Any]) -> Any:
    """``functools.cache`` whose first computation of a key is the only one.

    With plain ``cache`` two threads that miss at once both compute and the last to
    finish is kept: if a source file changes between their reads (an edit during a
    run), two lanes key the same stage differently within one process and the cache
    record one wrote is never found again (issue 32's intermittent re-run misses).
    Here the computation runs under :data:`_DIGEST_LOCK`, so every caller of a key in
    a process sees the value the first one computed. ``cache_clear`` as ``cache``'s.
    """
    cached = cache(fn)

    @wraps(fn)
    def once(*args: Any, **kwargs: Any) -> Any:
        with _DIGEST_LOCK:
            return cached(*args, **kwargs)

    once.cache_clear = cached.cache_clear  # type: ignore[attr-defined]
    once.cache_info = cached.cache_info  # type: ignore[attr-defined]
    return once


_DOCSTRING_OWNERS = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)


def syntax_dump(tree: ast.AST) -> str:
    r"""The behaviour-bearing form of a parsed module: its AST without docstrings.

    Comments and blank lines are gone with parsing; the docstring of the
    module, of every class and of every function is removed here (a body
    left empty becomes ``pass``, which behaves the same); line and column
    numbers are left out (``include_attributes=False``). So an edit of a
    comment, a docstring or the layout gives the same dump, and any change
    of a name, a constant, an operator or a statement gives another.
    The tree is modified in place.

    >>> a = ast.parse('def f(x):\n    "Twice."\n    return 2 * x  # double\n')
    >>> b = ast.parse('\n\ndef f(x):\n    return 2*x\n')
    >>> syntax_dump(a) == syntax_dump(b)
    True
    >>> syntax_dump(a) == syntax_dump(ast.parse('def f(x):\n    return 3 * x\n'))
    False
    """
    for node in ast.walk(tree):
        _drop_docstring(node)
    return ast.dump(tree, annotate_fields=True, include_attributes=False)


def _drop_docstring(node: ast.AST) -> None:
    """Remove the docstring of a module, class or function node (in place)."""
    if not isinstance(node, _DOCSTRING_OWNERS) or not node.body:
        return
    first = node.body[0]
    if (
        isinstance(first, ast.Expr)
        and isinstance(first.value, ast.Constant)
        and isinstance(first.value.value, str)
    ):
        node.body = node.body[1:] or [ast.Pass()]


@dataclass(frozen=True)
class _ModuleSyntax:
    """What the digests need from one module's source: its imports and its syntax.

    ``imports``: the project modules it imports; ``lazy``: those imported only
    by a module-level ``__getattr__`` (PEP 562: run when an attribute the
    module does not define is asked for); ``requests``: ``(module, name)``
    for every name it takes from a project module (``from m import name``,
    ``m.name`` after ``import m``); ``defined``: the names its top level
    binds; ``packages``: the top-level names of the other packages it
    imports (``numpy``, ``skimage``, ...).
    """

    imports: frozenset[str]
    lazy: frozenset[str]
    requests: frozenset[tuple[str, str]]
    defined: frozenset[str]
    packages: frozenset[str]
    syntax_sha256: str


#: Attributes every module has without binding them.
_MODULE_ATTRIBUTES = frozenset(
    {"__name__", "__file__", "__doc__", "__path__", "__spec__", "__loader__", "__package__",
     "__dict__", "__builtins__", "__cached__"}
)  # fmt: skip


def _top_level_names(body: list[ast.stmt]) -> set[str]:
    """Names a module body binds (into ``if``/``try``/``with`` blocks, not functions)."""
    names: set[str] = set()
    for node in body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update((a.asname or a.name.split(".")[0]) for a in node.names)
        elif isinstance(node, ast.Assign | ast.AnnAssign | ast.AugAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                names.update(n.id for n in ast.walk(t) if isinstance(n, ast.Name))
        elif isinstance(node, ast.If | ast.Try | ast.With):
            for block in ("body", "orelse", "finalbody"):
                names |= _top_level_names(getattr(node, block, []))
            for handler in getattr(node, "handlers", []):
                names |= _top_level_names(handler.body)
    return names


def _project_modules(found: set[str], root: Path) -> set[str]:
    out: set[str] = set()
    for mod in found:
        if mod.split(".")[0] in PROJECT_PACKAGES:
            out.update(m for m in _with_parents(mod) if _module_file(m, root) is not None)
    return out


@dataclass(frozen=True)
class _SourceFacts:
    """What one module's source says by itself, before any lookup under a root.

    ``found`` / ``found_lazy``: the modules its import statements name (the
    latter inside a module-level ``__getattr__``); ``from_names``: ``(base,
    name, lazy)`` for every ``from base import name`` of a project package (a
    submodule or a name, told apart under a root); ``attributes``: ``(module, name)`` for every
    ``m.name`` after ``import m`` of a project module.
    """

    found: frozenset[str]
    found_lazy: frozenset[str]
    from_names: tuple[tuple[str, str, bool], ...]
    attributes: frozenset[tuple[str, str]]
    defined: frozenset[str]
    packages: frozenset[str]
    syntax_sha256: str


@cache
def _source_facts(name: str, is_package: bool, source: bytes) -> _SourceFacts:
    """Parse one module's source once per process and content (wherever the file lies)."""
    with _AST_LOCK:
        tree = ast.parse(source, filename=name)
    package = name if is_package else name.rpartition(".")[0]
    getattr_fn = [
        n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "__getattr__"
    ]
    in_getattr = {id(n) for fn in getattr_fn for n in ast.walk(fn)}
    found: set[str] = set()
    found_lazy: set[str] = set()
    from_names: list[tuple[str, str, bool]] = []
    absolute: set[str] = set()  # top-level names of absolute imports
    bound: dict[str, str] = {}  # local name -> project module, by ``import m``
    attributes: list[ast.Attribute] = []
    for node in ast.walk(tree):  # one walk: the imports, and docstrings dropped
        _drop_docstring(node)
        lazy = id(node) in in_getattr
        into = found_lazy if lazy else found
        if isinstance(node, ast.Import):
            into.update(alias.name for alias in node.names)
            absolute.update(alias.name.split(".")[0] for alias in node.names)
            for alias in node.names:
                if alias.name.split(".")[0] in PROJECT_PACKAGES:
                    local = alias.asname or alias.name.split(".")[0]
                    bound[local] = alias.name if alias.asname else alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            if not node.level and node.module:
                absolute.add(node.module.split(".")[0])
            if node.level:
                anchor = package.split(".") if package else []
                anchor = anchor[: len(anchor) - (node.level - 1)] if node.level > 1 else anchor
                base = ".".join([*anchor, *([node.module] if node.module else [])])
            else:
                base = node.module or ""
            into.add(base)
            if base.split(".")[0] in PROJECT_PACKAGES:  # a submodule or a name: per root
                from_names.extend((base, alias.name, lazy) for alias in node.names)
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            attributes.append(node)
    bound_attributes = {
        (bound[node.value.id], node.attr)  # type: ignore[attr-defined]
        for node in attributes
        if node.value.id in bound  # type: ignore[attr-defined]
    }
    dump = ast.dump(tree, annotate_fields=True, include_attributes=False)  # as syntax_dump
    return _SourceFacts(
        found=frozenset(found),
        found_lazy=frozenset(found_lazy),
        from_names=tuple(from_names),
        attributes=frozenset(bound_attributes),
        defined=frozenset(_top_level_names(tree.body) | _MODULE_ATTRIBUTES),
        packages=frozenset(absolute - set(PROJECT_PACKAGES)),
        syntax_sha256=hashlib.sha256(dump.encode()).hexdigest(),
    )


@cache
def _parse_module(name: str, path_str: str, root_str: str, source: bytes) -> _ModuleSyntax:
    """One module's imports (resolved under ``root``) and syntax digest.

    The parse (:func:`_source_facts`) is shared by every root holding the same
    source; only the lookups of submodules (``from pkg import mod``) are per root.
    """
    path, root = Path(path_str), Path(root_str)
    try:
        facts = _source_facts(name, path.name == "__init__.py", source)
    except SyntaxError as exc:
        exc.filename = path_str
        raise
    found, found_lazy = set(facts.found), set(facts.found_lazy)
    requests: set[tuple[str, str]] = set()
    for base, alias, lazy in facts.from_names:
        # ``from pkg import mod`` imports the submodule ``pkg.mod``
        if _module_file(f"{base}.{alias}", root) is not None:
            (found_lazy if lazy else found).add(f"{base}.{alias}")
        else:
            requests.add((base, alias))
    for module, attr in facts.attributes:  # ``m.name`` after ``import m``
        if (module, attr) not in requests and _module_file(f"{module}.{attr}", root) is None:
            requests.add((module, attr))
    out = _project_modules(found, root)
    lazy_out = _project_modules(found_lazy, root) - out
    return _ModuleSyntax(
        imports=frozenset(out),
        lazy=frozenset(lazy_out),
        requests=frozenset(r for r in requests if r[0].split(".")[0] in PROJECT_PACKAGES),
        defined=facts.defined,
        packages=facts.packages,
        syntax_sha256=facts.syntax_sha256,
    )


@_once_per_process
def module_closure(roots: tuple[str, ...], root: str | None = None) -> tuple[str, ...]:
    """All project modules that importing ``roots`` executes, sorted.

    An AST walk over the import statements (top level and inside functions)
    of the project packages :data:`PROJECT_PACKAGES`; third-party imports are
    ignored. The imports of a module-level ``__getattr__`` (PEP 562, as
    ``tumor3d/__init__.py`` imports :mod:`tumor3d.api` on first use of
    ``tumor3d.reconstruct``) count only when a module of the closure asks
    that module for a name its top level does not bind (``from tumor3d
    import reconstruct``, ``tumor3d.reconstruct``): importing ``tumor3d``
    does not run them. Cached: computed once per process.

    Parameters
    ----------
    roots : tuple of str
        Dotted module names, e.g. ``("tumor3d.tasks.surface",)``.
    root : str, optional
        Folder holding the packages; default :data:`PROJECT_ROOT` (a test may
        point it at a temporary copy).

    Returns
    -------
    tuple of str
        Dotted module names, the roots and their parent packages included.

    Raises
    ------
    ValueError
        If a root module has no source file under ``root``.
    """
    base = Path(root) if root is not None else PROJECT_ROOT
    seen: dict[str, _ModuleSyntax] = {}
    todo: list[str] = []
    for name in roots:
        if _module_file(name, base) is None:
            raise ValueError(f"cannot locate the source of module {name!r} under {base}")
        todo.extend(_with_parents(name))
    while todo:
        while todo:
            name = todo.pop()
            if name in seen:
                continue
            path = _module_file(name, base)
            if path is None:
                continue
            seen[name] = _parse_module(name, str(path), str(base), path.read_bytes())
            todo.extend(seen[name].imports - seen.keys())
        # a package's lazy imports (PEP 562 ``__getattr__``) run when a module of the
        # closure asks it for a name its top level does not bind
        for module, name in {r for info in seen.values() for r in info.requests}:
            info = seen.get(module)
            if info is not None and name not in info.defined:
                todo.extend(info.lazy - seen.keys())
    return tuple(sorted(seen))


@_once_per_process
def code_digest(
    roots: tuple[str, ...], root: str | None = None, *, include_codecs: bool = False
) -> str:
    """SHA-256 of :data:`ARTIFACT_FORMAT_VERSION` and the code of the closure of ``roots``.

    Each module contributes its name and the digest of its syntax tree
    without docstrings (:func:`syntax_dump`: comments, docstrings and blank
    lines do not count; any change of behaviour does), plus the bytes of
    its :data:`DATA_FILES`. Store codecs in :data:`FORMAT_MODULES`
    contribute only through the format version, unless ``include_codecs``
    (the publish key: they encode published files too). Cached: computed
    once per process (and each module parsed once per process and content).
    """
    base = Path(root) if root is not None else PROJECT_ROOT
    h = hashlib.sha256(f"artifact-format={ARTIFACT_FORMAT_VERSION}\0".encode())
    for name in module_closure(roots, root):
        if name in FORMAT_MODULES and not include_codecs:
            continue
        path = _module_file(name, base)
        assert path is not None  # the closure holds only located modules
        h.update(name.encode() + b"\0")
        h.update(_syntax_digest_of(name, path, base).encode())
        h.update(b"\0")
        for rel in DATA_FILES.get(name, ()):
            data = base / rel
            h.update(rel.encode() + b"\0")
            h.update(data.read_bytes() if data.is_file() else b"<missing>")
            h.update(b"\0")
    return h.hexdigest()


@_once_per_process
def closure_packages(roots: tuple[str, ...], root: str | None = None) -> tuple[str, ...]:
    """The numerical distributions the closure of ``roots`` imports, sorted.

    The packages of :data:`tumor3d.storage.versions.NUMERICAL_PACKAGES` named by an
    import statement (any depth) of a module whose code enters the digest
    (store codecs in :data:`FORMAT_MODULES` excluded, as their code is),
    mapped to their distributions (``skimage`` -> ``scikit-image``; numba
    with llvmlite). Their versions enter the stage's key (:class:`StageCode`).
    Cached: computed once per process.
    """
    base = Path(root) if root is not None else PROJECT_ROOT
    names: set[str] = set()
    for name in module_closure(roots, root):
        if name in FORMAT_MODULES:
            continue
        path = _module_file(name, base)
        assert path is not None  # the closure holds only located modules
        names |= _parse_module(name, str(path), str(base), path.read_bytes()).packages
    return tuple(sorted({d for n in names for d in NUMERICAL_PACKAGES.get(n, ())}))


def package_versions(roots: tuple[str, ...], root: str | None = None) -> dict[str, str]:
    """Distribution -> installed version, for :func:`closure_packages` of ``roots``.

    Read from :func:`tumor3d.storage.versions.versions`, the one function that
    provenance and the publish key read too.
    """
    installed = versions()
    return {d: installed.get(d, "not installed") for d in closure_packages(roots, root)}


def fingerprint(value: Any) -> Any:
    """The JSON-able identity of a task input, as it enters a cache key.

    Artifact references are reduced to their content digest; pydantic models
    to their fields (``ArtifactRef`` fields nested in them included);
    mappings and sequences recursively. A model may list fields that do not
    identify its content (such as a file location) in a ``__cache_exclude__``
    class attribute.

    Raises
    ------
    TypeError
        For any other type (arrays must never enter a key).
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


def _sha(document: Any) -> str:
    return hashlib.sha256(canonical_dumps(document).encode()).hexdigest()


@dataclass
class StageCode(CachePolicy):
    """Key part: stage name, artifact format version, the stage's code closure and packages.

    The packages: the versions of the numerical distributions the closure
    imports (:func:`package_versions`), so an upgrade of scikit-image
    recomputes the stages whose code calls it, and only those.

    Parameters
    ----------
    stage : str
        Stage name.
    modules : tuple of str
        Root modules of the closure (the stage's adapter module).
    root : str, optional
        Source folder (tests only); default :data:`PROJECT_ROOT`.
    """

    stage: str = ""
    modules: tuple[str, ...] = field(default_factory=tuple)
    root: str | None = None

    def compute_key(
        self, task_ctx: Any, inputs: dict[str, Any], flow_parameters: dict[str, Any], **kw: Any
    ) -> str | None:
        """Digest of the stage's name, code and numerical packages' versions."""
        return _sha(
            {
                "stage": self.stage,
                "code": code_digest(self.modules, self.root),
                "packages": package_versions(self.modules, self.root),
            }
        )


@dataclass
class StageConfig(CachePolicy):
    """Key part: the stage's configuration model (input ``config``), if it has one."""

    parameter: str = "config"

    def compute_key(
        self, task_ctx: Any, inputs: dict[str, Any], flow_parameters: dict[str, Any], **kw: Any
    ) -> str | None:
        """Digest of the configuration's fields; None when the stage takes none."""
        if self.parameter not in inputs:
            return None
        return _sha({"config": fingerprint(inputs[self.parameter])})


@dataclass
class InputArtifacts(CachePolicy):
    """Key part: every input except the configuration and :data:`IGNORED_INPUTS`."""

    exclude: frozenset[str] = frozenset({"config"}) | IGNORED_INPUTS

    def compute_key(
        self, task_ctx: Any, inputs: dict[str, Any], flow_parameters: dict[str, Any], **kw: Any
    ) -> str | None:
        """Digest of the input references and values."""
        kept = {k: fingerprint(v) for k, v in sorted(inputs.items()) if k not in self.exclude}
        return _sha({"inputs": kept})


def stage_cache_policy(
    stage: str, modules: tuple[str, ...], *, root: str | None = None
) -> CachePolicy:
    """The cache policy of one stage: code + configuration + input artifacts.

    The single place where a stage's key is defined; a key is
    ``policy.compute_key(None, inputs, {})``.
    """
    return StageCode(stage=stage, modules=modules, root=root) + StageConfig() + InputArtifacts()
