"""Benchmark: a cached cohort re-run after a docstring edit (all hits), and a behaviour edit.

    python benchmarks/bench_docstring_rerun.py [--n 3] [--workers 2] [--slices 16] [--matrix 128]
        [--doc-module tumor3d/imaging/scan.py]
        [--behaviour-module tumor3d/geometry/brain_surface.py]
        [--behaviour-constant MAX_GRID_VOXELS] [--tmp DIR] [--keep] [--no-warmup]

Issue 31 asks for a measure of "a cached re-run of a cohort after a docstring edit
(all hits)": stage cache keys hash each stage's code closure as a syntax tree
without comments and docstrings (:mod:`tumor3d.tasks.caching`). This script runs,
end to end and on phantom patients (seeds 0.., small by default as the cohort
tests' phantoms):

1. ``first``: the cohort into a fresh output folder and store (every stage computes);
2. ``doc edit``: the same cohort into the same store after editing, in
   ``--doc-module`` (a module in every stage's code closure, checked), the module
   docstring, a function's or class's docstring, an existing comment, plus a new
   comment line and a blank line: expected all hits;
3. ``behaviour edit``: the same again after adding 1 to the integer constant
   ``--behaviour-constant`` of ``--behaviour-module`` (a module in some stages'
   closures only): expected misses are exactly the stages whose closure holds it
   (read from :func:`tumor3d.tasks.stages.stage_modules` before the edit). The
   default constant (the brain surface's grid size cap, far above a phantom's grid)
   changes no output, so no stage downstream misses for a changed input.

Hits and misses are read as the cohort re-run test reads them
(``tests/flows/test_cohort_flow.py``): ``StageRun.cached`` of every stage of every
patient in :func:`tumor3d.flows.cohort.run_cohort`'s result (a rejected hit,
``repaired``, counts as a miss). Each stage's code digest and numerical package
versions (the key's :class:`~tumor3d.tasks.caching.StageCode` part) are recorded
after every run, so a stage that misses can be traced to the component that moved.

Nothing in this repository is edited: the tracked files of its working tree
(``git ls-files``) are copied to a temporary folder (``storage/``, ``tasks/`` and
``flows/`` under ``tumor3d/``, as a wheel installs them), and every run is a fresh
subprocess (so edited source is imported again) with that copy first on
``sys.path`` and on ``PYTHONPATH`` (the render worker's). The virtual
environment's editable install maps ``tumor3d`` to this repository through a
finder appended to ``sys.meta_path`` after ``PathFinder``, so a ``sys.path``
entry already wins; the child removes that finder anyway, and checks that
``tumor3d.__file__`` and every loaded ``tumor3d`` module lie in the copy. The
Prefect home, the state folder (one background server, started from the copy for
the three runs: its start-up is excluded) and the store are temporary too; the
numba kernels of the copy are compiled first (``python -m tumor3d.warmup``,
timed apart) unless ``--no-warmup``. Prints a Markdown table: per stage, hits /
misses in each run; the cohort's wall time (inside the child) and the child
process's (imports included).
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tokenize
from io import StringIO
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Run in each child as ``python -c``: argv = [copy, action, json_out, *args].
_CHILD = r"""
import json, sys, time
from pathlib import Path

copy = Path(sys.argv[1]).resolve()
sys.path[:] = [str(copy)] + [p for p in sys.path if p not in ("", str(copy))]
sys.meta_path[:] = [f for f in sys.meta_path if "__editable__" not in getattr(f, "__module__", "")]
import tumor3d

assert Path(tumor3d.__file__).resolve().is_relative_to(copy), tumor3d.__file__
action, out = sys.argv[2], Path(sys.argv[3])
args = json.loads(sys.argv[4])
doc = {"tumor3d_file": tumor3d.__file__}

if action == "setup":
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.manifest import write_manifest
    from tumor3d.storage.phantom_io import write_phantom_patient
    from tumor3d.tasks.stages import STAGES, stage_modules

    rows = []
    for seed in range(args["n"]):
        pid = f"doc{seed:03d}"
        patient = make_phantom_patient(
            seed, patient_id=pid, n_slices=args["slices"],
            matrix_size=(args["matrix"], args["matrix"]),
        )
        rows.append(write_phantom_patient(patient, Path(args["inputs"]) / pid))
    write_manifest(rows, args["manifest"])
    doc["closures"] = {name: list(stage_modules(name)) for name in STAGES}
elif action == "run":
    from tumor3d.flows.cohort import run_cohort
    from tumor3d.tasks.caching import package_versions
    from tumor3d.tasks.stages import STAGES

    t = time.perf_counter()
    result = run_cohort(
        args["manifest"], args["out"], workers=args["workers"], store_dir=args["store"]
    )
    doc["wall_s"] = time.perf_counter() - t
    doc["exit_code"] = result.exit_code
    doc["patients"] = [
        {
            "patient_id": p.patient_id, "status": p.status, "error": p.error,
            "recomputed": p.recomputed,
            "stages": [
                {"stage": s.stage, "cached": s.cached, "repaired": s.repaired}
                for s in p.stages
            ],
        }
        for p in result.patients
    ]
    doc["keys"] = {
        name: {"code": spec.code_digest, "packages": package_versions((spec.adapter_module,))}
        for name, spec in STAGES.items()
    }
    stray = sorted(
        name for name, m in list(sys.modules.items())
        if name.split(".")[0] == "tumor3d" and getattr(m, "__file__", None)
        and not Path(m.__file__).resolve().is_relative_to(copy)
    )
    assert not stray, f"modules imported from outside the copy: {stray}"
    doc["modules_checked"] = sum(1 for n in sys.modules if n.split(".")[0] == "tumor3d")
out.write_text(json.dumps(doc))
"""


#: The repository's top-level folders that are sub-packages of ``tumor3d`` (pyproject.toml's
#: ``package-dir``): nested under the copy's ``tumor3d/`` as a built wheel nests them.
MAPPED_FOLDERS = ("storage", "tasks", "flows")


def _copy_tree(dest: Path) -> None:
    """The tracked files of this repository's working tree (uncommitted edits included),
    laid out as installed: :data:`MAPPED_FOLDERS` under ``tumor3d/``, so that ``sys.path``
    alone imports the whole namespace from the copy."""
    listed = subprocess.run(
        ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
    ).stdout.decode()
    for rel in filter(None, listed.split("\0")):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    for folder in MAPPED_FOLDERS:
        if (dest / folder / "__init__.py").is_file():
            shutil.move(dest / folder, dest / "tumor3d" / folder)


def _child(copy: Path, action: str, args: dict, env: dict[str, str], log: Path) -> dict:
    out = log.with_suffix(".json")
    t = time.perf_counter()
    with log.open("w") as fh:
        proc = subprocess.run(
            [sys.executable, "-c", _CHILD, str(copy), action, str(out), json.dumps(args)],
            cwd=copy, env=env, stdout=fh, stderr=subprocess.STDOUT, check=False,
        )  # fmt: skip
    if proc.returncode != 0:
        sys.exit(f"{action} failed (exit {proc.returncode}); its output: {log}")
    doc = json.loads(out.read_text())
    doc["process_s"] = time.perf_counter() - t
    if not Path(doc["tumor3d_file"]).resolve().is_relative_to(copy.resolve()):
        sys.exit(f"the child imported {doc['tumor3d_file']}, not the copy's tumor3d")
    return doc


def _edit_docs(path: Path) -> list[str]:
    """Edit docstrings and comments of ``path`` in place; the edits made."""
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    tree = ast.parse(text)
    made: list[str] = []
    inserts: dict[int, str] = {}  # 0-based line -> text inserted before it
    # the module's docstring and the first function's or class's, each written with its
    # closing quotes on a line of their own: a line is added before those quotes
    defs = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.ClassDef)]
    for kind, owners in (("module", [tree]), ("definition", defs)):
        for node in owners:
            first = node.body[0] if node.body else None
            if not (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
                and first.end_lineno is not None
                and lines[first.end_lineno - 1].strip() in ('"""', "'''")
            ):
                continue
            closing = lines[first.end_lineno - 1]
            indent = closing[: len(closing) - len(closing.lstrip())]
            inserts[first.end_lineno - 1] = (
                f"\n{indent}Edited by bench_docstring_rerun.py: a docstring changes no key.\n"
            )
            name = getattr(node, "name", "")
            made.append(f"docstring of {kind} {name}".replace("  ", " ").strip())
            break
    comments = [
        tok for tok in tokenize.generate_tokens(StringIO(text).readline)
        if tok.type == tokenize.COMMENT
    ]  # fmt: skip
    if comments:
        row, col = comments[0].start
        old = lines[row - 1]
        lines[row - 1] = old.rstrip("\n") + " (edited: a comment changes no key)\n"
        made.append(f"comment of line {row}")
    after_doc = tree.body[1].lineno - 1 if len(tree.body) > 1 else len(lines)
    inserts[after_doc] = inserts.get(after_doc, "") + "\n# A comment added by the benchmark.\n"
    made.append("new comment line and blank lines")
    new = "".join(inserts.get(i, "") + line for i, line in enumerate(lines))
    ast.parse(new)  # still valid
    path.write_text(new)
    return made


def _edit_constant(path: Path, name: str) -> str:
    """Add 1 to the module-level integer constant ``name`` of ``path``; the edit made."""
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    for node in ast.parse(text).body:
        targets = node.targets if isinstance(node, ast.Assign) else []
        if isinstance(node, ast.AnnAssign):
            targets = [node.target]
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            value = node.value
            if not (isinstance(value, ast.Constant) and type(value.value) is int):
                sys.exit(f"{name} in {path} is not an integer constant")
            assert value.lineno == value.end_lineno
            line = lines[value.lineno - 1]
            new = f"{value.value + 1:_}"
            lines[value.lineno - 1] = line[: value.col_offset] + new + line[value.end_col_offset :]
            path.write_text("".join(lines))
            return f"{name} = {new} (was {value.value:_})"
    sys.exit(f"no module-level {name} in {path}")


def _counts(run: dict) -> dict[str, list[int]]:
    """Stage -> [hits, misses] over the cohort's patients."""
    out: dict[str, list[int]] = {}
    for p in run["patients"]:
        if p["status"] == "failed":
            sys.exit(f"{p['patient_id']} failed: {p['error']}")
        for s in p["stages"]:
            hit = s["cached"] and not s["repaired"]
            out.setdefault(s["stage"], [0, 0])[0 if hit else 1] += 1
    return out


def _row(label: str, cells: list[str]) -> str:
    return f"| {label} | " + " | ".join(cells) + " |"


def _cell(c: list[int]) -> str:
    return f"{c[0]} / {c[1]}"


def _moved(before: dict, after: dict) -> list[str]:
    return [
        f"{stage} ({', '.join(k for k in ('code', 'packages') if before[stage][k] != v[k])})"
        for stage, v in after.items()
        if v != before[stage]
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=3, help="phantom patients (seeds 0..n-1)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--slices", type=int, default=16, help="phantom slices")
    parser.add_argument("--matrix", type=int, default=128, help="phantom matrix (pixels a side)")
    parser.add_argument("--doc-module", default="tumor3d/imaging/scan.py")
    parser.add_argument("--behaviour-module", default="tumor3d/geometry/brain_surface.py")
    parser.add_argument("--behaviour-constant", default="MAX_GRID_VOXELS")
    parser.add_argument("--tmp", type=Path, help="scratch folder (default: a new temporary one)")
    parser.add_argument("--keep", action="store_true", help="keep the scratch folder")
    parser.add_argument("--no-warmup", action="store_true", help="skip the numba warm-up")
    args = parser.parse_args()

    if args.tmp is not None:
        args.tmp.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="tumor3d-bench-docrerun-", dir=args.tmp))
    copy = tmp / "src"
    _copy_tree(copy)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_API_")}
    env.update(
        PYTHONPATH=str(copy), PREFECT_HOME=str(tmp / "prefect"), TUMOR3D_HOME=str(tmp / "home"),
        TUMOR3D_NO_DAEMON="1", PREFECT_SERVER_ANALYTICS_ENABLED="false",
        PREFECT_LOGGING_LEVEL="WARNING",
    )  # fmt: skip
    env.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "240")
    common = {
        "manifest": str(tmp / "manifest.csv"), "out": str(tmp / "out"),
        "store": str(tmp / "store"), "workers": args.workers,
    }  # fmt: skip
    cli = [sys.executable, "-m", "tumor3d.flows.cli"]
    logs = tmp / "logs"
    logs.mkdir()
    doc_path, beh_path = copy / args.doc_module, copy / args.behaviour_module
    doc_mod = args.doc_module.removesuffix(".py").replace("/", ".").removesuffix(".__init__")
    beh_mod = args.behaviour_module.removesuffix(".py").replace("/", ".").removesuffix(".__init__")
    runs: dict[str, dict] = {}
    try:
        setup = _child(
            copy, "setup",
            {"n": args.n, "slices": args.slices, "matrix": args.matrix,
             "inputs": str(tmp / "inputs"), "manifest": common["manifest"]},
            env, logs / "setup.log",
        )  # fmt: skip
        print(f"the child imports {setup['tumor3d_file']}")
        closures = setup["closures"]
        stages = list(closures)
        if missing := [s for s in stages if doc_mod not in closures[s]]:
            print(f"note: {doc_mod} is not in the closure of {', '.join(missing)}")
        expected = [s for s in stages if beh_mod in closures[s]]
        print(f"{beh_mod} is in the closure of {len(expected)} of {len(stages)} stages")
        warm_s = 0.0
        if not args.no_warmup:
            t = time.perf_counter()
            with (logs / "warmup.log").open("w") as fh:
                subprocess.run(
                    [sys.executable, "-m", "tumor3d.warmup"], cwd=copy, env=env, check=True,
                    stdout=fh, stderr=subprocess.STDOUT,
                )  # fmt: skip
            warm_s = time.perf_counter() - t
        t = time.perf_counter()
        subprocess.run([*cli, "server", "start"], cwd=copy, env=env, check=True,
                       stdout=subprocess.DEVNULL)  # fmt: skip
        server_s = time.perf_counter() - t

        runs["first"] = _child(copy, "run", common, env, logs / "first.log")
        raw_before = hashlib.sha256(doc_path.read_bytes()).hexdigest()
        doc_edits = _edit_docs(doc_path)
        assert hashlib.sha256(doc_path.read_bytes()).hexdigest() != raw_before
        runs["doc"] = _child(copy, "run", common, env, logs / "doc.log")
        beh_edit = _edit_constant(beh_path, args.behaviour_constant)
        runs["behaviour"] = _child(copy, "run", common, env, logs / "behaviour.log")
    finally:
        subprocess.run([*cli, "server", "stop"], cwd=copy, env=env, check=False,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)

    counts = {name: _counts(run) for name, run in runs.items()}
    titles = {
        "first": "first (fresh store)",
        "doc": f"after docstring + comment edit of `{args.doc_module}`",
        "behaviour": f"after behaviour edit `{beh_edit}` of `{args.behaviour_module}`",
    }
    lines = [
        f"{args.n} phantoms ({args.slices} slices of {args.matrix} x {args.matrix}), "
        f"{args.workers} workers, Python {sys.version.split()[0]}; numba warm-up "
        f"{warm_s:.1f} s and server start-up {server_s:.1f} s excluded. Doc edit: "
        f"{'; '.join(doc_edits)}.",
        "",
        _row("stage hits / misses", [titles[r] for r in runs]),
        "|---|" + "---:|" * len(runs),
    ]
    for stage in stages:
        lines.append(_row(stage, [_cell(counts[r].get(stage, [0, 0])) for r in runs]))
    totals = {r: [sum(c[i] for c in counts[r].values()) for i in (0, 1)] for r in runs}
    lines.append(_row("**all stages**", [f"**{_cell(totals[r])}**" for r in runs]))
    lines.append(_row("cohort wall time (s)", [f"{runs[r]['wall_s']:.1f}" for r in runs]))
    lines.append(
        _row(
            "process wall time, imports included (s)", [f"{runs[r]['process_s']:.1f}" for r in runs]
        )
    )
    moved = [
        ", ".join(_moved(runs[a]["keys"], runs[b]["keys"])) or "none"
        for a, b in (("first", "doc"), ("doc", "behaviour"))
    ]
    lines.append(_row("stage keys' code part moved (vs the run before)", ["–", *moved]))
    missed = {r: [s for s in stages if counts[r].get(s, [0, 0])[1]] for r in runs}
    lines.append(
        _row(
            "stages that missed",
            ["all" if missed[r] == stages else ", ".join(missed[r]) or "none" for r in runs],
        )
    )
    lines.append(_row("stages expected to miss", ["all", "none", ", ".join(expected)]))
    reasons = {r: sorted({str(p["recomputed"]) for p in runs[r]["patients"]}) for r in runs}
    lines.append(_row("patients' `recomputed`", ["; ".join(reasons[r]) for r in runs]))
    print("\n".join(lines))
    ok = missed["first"] == stages and not missed["doc"] and missed["behaviour"] == expected
    print(f"\nverdict: {'as expected' if ok else 'NOT as expected'}")
    if not ok:
        sys.exit(1)


if __name__ == "__main__":
    main()
