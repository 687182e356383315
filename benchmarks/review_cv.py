"""Choose the learned method's review limits by cross-validation by patient.

Reads the per-case rows of ``benchmarks/learned_cv.py --json`` (out-of-fold:
every case was segmented by a model that never saw its patient; a figure
added after the run: ``benchmarks/review_figures.py``) and, fold by fold,
chooses the limits of the judged figures (default: those of
``REVIEW_LIMITS["with_net"]``, :data:`tumor3d.learned.review.REVIEW_LIMITS`) on the
other folds' cases, then judges them on the held-out fold:

- a case whose volume is off by more than 25 % should be flagged (target:
  >= 80 % of them),
- a case within 10 % should not (target: <= 25 % flagged).

The choice maximises the share of > 25 % cases flagged among the limits
that flag at most 25 % of the within-10 % cases of the choosing folds
(ties: fewer flags, then the first in :data:`GRID` order). The final limits
are chosen the same way on every case.

With ``--forest-alone ROWS`` (the same command's rows without the U-Net,
``segment.learned_cnn: off``), the two kinds of segmentation get their own
limits, as the pipeline judges them (:func:`tumor3d.learned.review.review_kind`):
fold by fold, the ``with_net`` limits are chosen on the other folds' rows of the
shipped method, then the forest alone's own figures (default: those of
``REVIEW_LIMITS["forest_alone"]`` that ``with_net`` lacks) on the other folds'
forest-alone rows, the shared limits fixed at the ``with_net`` choice; a held-out
row with a disagreement figure is judged by the first, one without by the second,
and the forest-alone rows by the second. The held-out flags are
:func:`tumor3d.learned.review.review_segmentation`'s own; the search over the
grid is vectorised and checked against it.

Usage::

    python benchmarks/review_cv.py /tmp/cv/learned.json
    python benchmarks/review_cv.py rows.json --measures uncertain_ratio mean_probability \\
        outside_ratio prior_agreement          # the limits judged before model_disagreement
    python benchmarks/review_cv.py learned.json --forest-alone forest.json   # as shipped
    python benchmarks/review_cv.py learned.json --forest-alone forest.json \\
        --default-rows auto_t2.json          # the default's T2 (robust) by its own doubts
    python benchmarks/review_cv.py learned.json --forest-alone forest.json \\
        --nested-alone uncertain_ratio prior_agreement uncertain_ratio,prior_agreement
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.learned.review import REVIEW_CHECKS, REVIEW_LIMITS, review_segmentation  # noqa: E402

#: The candidate limits of each figure.
GRID = {
    "uncertain_ratio": (0.4, 0.5, 0.6, 0.7, 0.8, 1.0, 1.2, 1.5, 2.0, 3.0),
    "mean_probability": (0.5, 0.6, 0.7, 0.75, 0.8, 0.85),
    "outside_ratio": (0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0),
    "prior_agreement": (0.0, 0.3, 0.5, 0.6, 0.7, 0.8),
    "model_disagreement": (0.1, 0.15, 0.2, 0.25, 0.3, 0.5, 1.0),
    "net_spread": (0.08, 0.1, 0.12, 0.15, 0.2, 0.25),
}
#: A row's figure that is missing or null (JSON of inf) reads as this.
_MISSING = {
    "uncertain_ratio": float("inf"),
    "outside_ratio": float("inf"),
    "mean_probability": float("nan"),
    "prior_agreement": 1.0,
    "model_disagreement": float("nan"),  # no U-Net: not judged
    "net_spread": float("nan"),  # no U-Net ensemble: not judged
}
MAX_GOOD_FLAGGED = 0.25


def _values(rows: list[dict], name: str) -> np.ndarray:
    miss = _MISSING[name]
    return np.array([miss if r.get(name) is None else float(r[name]) for r in rows], float)


def _figures(r: dict, measures) -> dict:
    fig = {k: float(_values([r], k)[0]) for k in measures}
    fig["volume_ml"] = 0.0
    return fig


def fixed_flags(rows: list[dict]) -> np.ndarray:
    """Rows flagged whatever the limits, as the run's status flags them
    (:func:`tumor3d.segmentation.review.review_status`): an empty segmentation (no tumour
    found asks a human to confirm there is none), or any of the row's ``doubts`` (the
    segmentation's caveats and the brain mask's notes: ``benchmarks/review_doubts.py``,
    ``learned_cv.py --method`` rows; rows without them count none). A caveat that only
    informs (``INFORMING_CAVEATS``: rows saved before it stopped doubting hold it) is not
    counted."""
    from tumor3d.segmentation.review import INFORMING_CAVEATS

    def doubted(r: dict) -> bool:
        return any(not d.startswith(INFORMING_CAVEATS) for d in r.get("doubts") or ())

    return np.array([float(r["est_ml"]) == 0.0 or doubted(r) for r in rows], bool)


def flags(rows: list[dict], limits: dict) -> np.ndarray:
    """``needs_review`` of each row judged by ``limits`` alone (review_segmentation's own:
    the row's other figures are not given to it, so its other limits do not apply), or
    a row :func:`fixed_flags` flags."""
    judged = [review_segmentation(_figures(r, limits), limits).needs_review for r in rows]
    return np.array(judged, bool) | fixed_flags(rows)


def _beyond(v: np.ndarray, limit: float, side: str) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return v > limit if side == "above" else (np.isfinite(v) & (v < limit))


def _flag_matrix(rows: list[dict], measures: tuple[str, ...], combos: np.ndarray) -> np.ndarray:
    """Flags (combination x row) of every combination of grid indices, vectorised."""
    out = np.zeros((len(combos), len(rows)), bool)
    out |= fixed_flags(rows)[None, :]
    for j, name in enumerate(measures):
        v = _values(rows, name)
        side = REVIEW_CHECKS[name][0]
        per = np.stack([_beyond(v, x, side) for x in GRID[name]])
        out |= per[combos[:, j]]
    return out


def _counts(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    err = np.abs(np.array([r["vol_err"] for r in rows], float))
    return err > 25, err <= 10


def choose(
    rows: list[dict], measures: tuple[str, ...] | None = None, fixed: dict | None = None
) -> dict:
    """The limits of ``measures`` chosen on ``rows`` (see the module docstring), the
    limits ``fixed`` judged beside them (and returned with them)."""
    measures = tuple(measures or REVIEW_LIMITS["with_net"])
    combos = np.array(list(itertools.product(*(range(len(GRID[k])) for k in measures))))
    f = _flag_matrix(rows, measures, combos)
    if fixed:
        f |= flags(rows, fixed)[None, :]
    bad, good = _counts(rows)
    caught, false, n = f[:, bad].sum(1), f[:, good].sum(1), f.sum(1)
    ok = false <= MAX_GOOD_FLAGGED * good.sum() if good.any() else np.ones(len(f), bool)
    if not ok.any():  # nothing keeps the within-10 % cases: the loosest limits
        best = np.array([0 if REVIEW_CHECKS[k][0] == "below" else -1 for k in measures])
        best = np.where(best < 0, [len(GRID[k]) - 1 for k in measures], best)
    else:
        top = np.flatnonzero(ok & (caught == caught[ok].max()))
        best = combos[top[np.argmin(n[top])]]  # argmin: the first of the fewest flags
    return {**(fixed or {}), **{k: GRID[k][i] for k, i in zip(measures, best, strict=True)}}


#: The sequence names a case's id may end with (``Brats18_X/flair``): its patient is the rest.
SEQUENCES = ("flair", "t2", "t1c", "t1")


def patient(case: str) -> str:
    """The patient of a row's ``case``: the id without its sequence (BraTS rows of
    one patient share it; an LGG head is its own patient)."""
    head, _, last = case.rpartition("/")
    return head if head and last in SEQUENCES else case


def _median_limits(chosen: list[dict]) -> dict:
    """Each figure's limit: the median grid index of ``chosen`` (an odd number of choices,
    so the median is one of the grid's values)."""
    return {k: GRID[k][int(np.median([GRID[k].index(c[k]) for c in chosen]))] for k in chosen[0]}


def bagged(pick, row_sets: list[list[dict]], n_boot: int, seed: int = 0):
    """``pick(*row_sets)``'s choice of limits, bagged: ``pick`` run on ``n_boot``
    bootstrap resamples of the patients (all rows of a drawn patient in every set,
    drawn together), each figure's limit the median of the chosen grid indices.
    ``pick`` returns a dict of limits or a tuple of them (each bagged on its own);
    ``n_boot`` must be odd."""
    if n_boot % 2 == 0:
        raise ValueError(f"n_boot must be odd (a median on the grid), got {n_boot}")
    patients = sorted({patient(r["case"]) for rs in row_sets for r in rs})
    by = [{p: [r for r in rs if patient(r["case"]) == p] for p in patients} for rs in row_sets]
    rng = np.random.default_rng(seed)
    chosen = []
    for _ in range(n_boot):
        draw = rng.integers(0, len(patients), len(patients))
        chosen.append(pick(*([r for i in draw for r in b[patients[i]]] for b in by)))
    if isinstance(chosen[0], tuple):
        return tuple(_median_limits([c[j] for c in chosen]) for j in range(len(chosen[0])))
    return _median_limits(chosen)


def _choose(rows: list[dict], measures: tuple[str, ...], bag: int) -> dict:
    return bagged(lambda rs: choose(rs, measures), [rows], bag) if bag else choose(rows, measures)


def rates(rows: list[dict], f: np.ndarray) -> tuple[float, float, int, int]:
    bad, good = _counts(rows)
    return (
        float(f[bad].mean()) if bad.any() else float("nan"),
        float(f[good].mean()) if good.any() else float("nan"),
        int(bad.sum()),
        int(good.sum()),
    )


def cross_validate(rows: list[dict], measures: tuple[str, ...] | None = None, bag: int = 0) -> dict:
    """Limits chosen fold by fold on the other folds, judged on the held-out fold.

    Returns ``lines`` (the printed report), ``all`` and ``real`` (every case;
    the cases but the phantoms): ``(share of the > 25 % cases flagged, share of
    the within-10 % cases flagged, number of each)``, ``fold_limits`` and
    ``final`` (the limits chosen on every case). ``bag``: the choice bagged over this
    many bootstrap resamples of the patients (:func:`bagged`; 0: not bagged).
    """
    measures = tuple(measures or REVIEW_LIMITS["with_net"])
    rows = [r for r in rows if np.isfinite(r["vol_err"])]
    folds = sorted({r["fold"] for r in rows})
    held_flags = np.zeros(len(rows), bool)
    lines, fold_limits = [f"judged: {', '.join(measures)}"], {}
    for k in folds:
        train = [r for r in rows if r["fold"] != k]
        lim = fold_limits[k] = _choose(train, measures, bag)
        idx = [i for i, r in enumerate(rows) if r["fold"] == k]
        held_flags[idx] = flags([rows[i] for i in idx], lim)
        lines.append(f"fold {k}: limits {lim}")
    caught, false, n_bad, n_good = every = rates(rows, held_flags)
    lines.append(
        f"\ncross-validated: {caught:.0%} of {n_bad} cases off by > 25 % flagged; "
        f"{false:.0%} of {n_good} within 10 % flagged"
    )
    for g in sorted({r["group"] for r in rows}):
        sel = [i for i, r in enumerate(rows) if r["group"] == g]
        c, fl, nb, ng = rates([rows[i] for i in sel], held_flags[sel])
        lines.append(f"  {g}: {c:.0%} of {nb} > 25 % flagged, {fl:.0%} of {ng} within 10 % flagged")
    real = [i for i, r in enumerate(rows) if r["group"] != "phantom"]
    real_rates = caught, false, n_bad, n_good = rates([rows[i] for i in real], held_flags[real])
    if len(real) < len(rows):
        lines.append(
            f"  real cases only: {caught:.0%} of {n_bad} > 25 % flagged, {false:.0%} of "
            f"{n_good} within 10 % flagged"
        )
    final = _choose(rows, measures, bag)
    # the vectorised search and the review itself agree on the chosen limits
    combo = np.array([[GRID[k].index(final[k]) for k in measures]])
    if not np.array_equal(_flag_matrix(rows, measures, combo)[0], flags(rows, final)):
        raise AssertionError("review_cv's vectorised flags differ from review_segmentation's")
    lines.append(f"\nfinal limits (every case): {final}")
    return {
        "lines": lines,
        "all": every,
        "real": real_rates,
        "fold_limits": fold_limits,
        "final": final,
    }


#: The forest alone's own figures by default: those of its limits the ``with_net`` set lacks.
ALONE_EXTRA = tuple(k for k in REVIEW_LIMITS["forest_alone"] if k not in REVIEW_LIMITS["with_net"])


def _has_net(r: dict) -> bool:
    return bool(np.isfinite(_values([r], "model_disagreement")[0]))


def _rate_lines(rows: list[dict], f: np.ndarray, what: str) -> list[str]:
    c, fl, nb, ng = rates(rows, f)
    out = [f"{what}: {c:.0%} of {nb} cases off by > 25 % flagged; {fl:.0%} of {ng} within 10 %"]
    for g in sorted({r["group"] for r in rows}):
        sel = [i for i, r in enumerate(rows) if r["group"] == g]
        c, fl, nb, ng = rates([rows[i] for i in sel], f[sel])
        out.append(f"  {g}: {c:.0%} of {nb} > 25 % flagged, {fl:.0%} of {ng} within 10 % flagged")
    real = [i for i, r in enumerate(rows) if r["group"] != "phantom"]
    c, fl, nb, ng = rates([rows[i] for i in real], f[real])
    out.append(f"  real cases only: {c:.0%} of {nb} > 25 % flagged, {fl:.0%} of {ng} within 10 %")
    return out


#: Figures that exist only with the U-Net (nan for a forest alone): never shared.
NET_ONLY = ("model_disagreement", "net_spread")


def _split_limits(
    rows: list[dict], forest_rows: list[dict], net_measures: tuple, extra: tuple, bag: int = 0
) -> tuple[dict, dict]:
    """The ``with_net`` limits chosen on ``rows``, the forest alone's on ``forest_rows``
    (its ``extra`` figures; the others but the disagreement fixed at the first choice),
    bagged over ``bag`` bootstrap resamples of the patients (0: not bagged)."""
    if bag:
        return bagged(
            lambda a, b: _split_limits(a, b, net_measures, extra), [rows, forest_rows], bag
        )
    net = choose(rows, net_measures)
    shared = {k: v for k, v in net.items() if k not in NET_ONLY and k not in extra}
    return net, choose(forest_rows, extra, fixed=shared) if extra else shared


def _split_flags(rows: list[dict], net: dict, alone: dict) -> np.ndarray:
    return np.array([flags([r], net if _has_net(r) else alone)[0] for r in rows], bool)


def cross_validate_split(
    rows: list[dict],
    forest_rows: list[dict],
    net_measures: tuple[str, ...] | None = None,
    extra: tuple[str, ...] | None = None,
    default_rows: list[dict] | None = None,
    bag: int = 0,
) -> dict:
    """The two kinds' limits chosen fold by fold (the module docstring), judged on the
    held-out fold. Returns ``lines``, ``all``/``real`` (the shipped rows, as
    :func:`cross_validate`), ``alone_all``/``alone_real`` (the forest-alone rows),
    ``fold_limits`` and ``final`` (``{"with_net": ..., "forest_alone": ...}`` on every case).

    ``default_rows``: the rows of the cases where the default (``segment.method: auto``)
    runs another method than the learned one (the robust method on real T2); they take
    the place of those cases' learned rows, flagged by :func:`fixed_flags` alone, in
    ``default_all``/``default_real`` (the review as the default ships it). ``bag``: each
    choice bagged over this many bootstrap resamples of the patients (:func:`bagged`)."""
    net_measures = tuple(net_measures or REVIEW_LIMITS["with_net"])
    extra = ALONE_EXTRA if extra is None else tuple(extra)
    rows = [r for r in rows if np.isfinite(r["vol_err"])]
    forest_rows = [r for r in forest_rows if np.isfinite(r["vol_err"])]
    held, held_alone = np.zeros(len(rows), bool), np.zeros(len(forest_rows), bool)
    lines = [f"with_net: {', '.join(net_measures)}; forest_alone adds: {', '.join(extra) or '-'}"]
    fold_limits = {}
    for k in sorted({r["fold"] for r in rows}):
        net, alone = fold_limits[k] = _split_limits(
            [r for r in rows if r["fold"] != k],
            [r for r in forest_rows if r["fold"] != k],
            net_measures,
            extra,
            bag,
        )
        idx = [i for i, r in enumerate(rows) if r["fold"] == k]
        held[idx] = _split_flags([rows[i] for i in idx], net, alone)
        idx = [i for i, r in enumerate(forest_rows) if r["fold"] == k]
        held_alone[idx] = flags([forest_rows[i] for i in idx], alone)
        lines.append(f"fold {k}: with_net {net}; forest_alone {alone}")
    lines += [""] + _rate_lines(rows, held, "cross-validated, shipped rows")
    lines += _rate_lines(forest_rows, held_alone, "cross-validated, forest-alone rows")
    net, alone = _split_limits(rows, forest_rows, net_measures, extra, bag)
    lines.append(f"\nfinal limits (every case): with_net {net}; forest_alone {alone}")
    real = [r["group"] != "phantom" for r in rows]
    real_alone = [r["group"] != "phantom" for r in forest_rows]
    out = {}
    if default_rows is not None:
        default_rows = [r for r in default_rows if np.isfinite(r["vol_err"])]
        other = {r["case"] for r in default_rows}
        keep = [i for i, r in enumerate(rows) if r["case"] not in other]
        both = [rows[i] for i in keep] + default_rows
        f = np.concatenate([held[keep], fixed_flags(default_rows)])
        both_real = np.array([r["group"] != "phantom" for r in both])
        out = {
            "default_all": rates(both, f),
            "default_real": rates(
                [r for r, x in zip(both, both_real, strict=True) if x], f[both_real]
            ),
        }
        lines += _rate_lines(
            both, f, f"cross-validated, as the default ships ({len(other)} cases by their doubts)"
        )
    return {
        **out,
        "lines": lines,
        "all": rates(rows, held),
        "real": rates([r for r, x in zip(rows, real, strict=True) if x], held[real]),
        "alone_all": rates(forest_rows, held_alone),
        "alone_real": rates(
            [r for r, x in zip(forest_rows, real_alone, strict=True) if x], held_alone[real_alone]
        ),
        "fold_limits": fold_limits,
        "final": {"with_net": net, "forest_alone": alone},
    }


def _best_set(train: list[dict], sets: list[tuple[str, ...]]) -> tuple[str, ...]:
    """:func:`nested`'s choice among ``sets`` on ``train`` (each cross-validated on it)."""
    keys = []
    for s in sets:
        caught, false, _, _ = cross_validate(train, s)["all"]
        keys.append((false <= MAX_GOOD_FLAGGED, caught, -false, -len(s)))
    return sets[max(range(len(sets)), key=keys.__getitem__)]  # ties: the first


def nested_alone(
    rows: list[dict],
    forest_rows: list[dict],
    sets: list[tuple[str, ...]],
    net_sets: list[tuple[str, ...]] | None = None,
) -> list[str]:
    """The choice of the forest alone's own figures among ``sets`` (``()``: none),
    itself cross-validated: outer fold ``k``, each set is cross-validated
    (:func:`cross_validate_split`) on the other folds, the one that catches most of
    their forest-alone > 25 % cases while flagging at most 25 % of their within-10 %
    ones (ties: fewer flagged, then fewer figures, then the first) gets its limits
    chosen on those folds and is judged on fold ``k``. With ``net_sets``, the
    ``with_net`` figures are first chosen among them on the other folds as
    :func:`nested` chooses (doubly nested), else they are ``REVIEW_LIMITS["with_net"]``'s."""
    rows = [r for r in rows if np.isfinite(r["vol_err"])]
    forest_rows = [r for r in forest_rows if np.isfinite(r["vol_err"])]
    held, held_alone = np.zeros(len(rows), bool), np.zeros(len(forest_rows), bool)
    lines = []
    for k in sorted({r["fold"] for r in rows}):
        train = [r for r in rows if r["fold"] != k]
        ftrain = [r for r in forest_rows if r["fold"] != k]
        net_set = _best_set(train, net_sets) if net_sets else tuple(REVIEW_LIMITS["with_net"])
        keys = []
        for s in sets:
            run = cross_validate_split(train, ftrain, net_set, extra=s)
            caught, false, _, _ = run["alone_all"]
            keys.append((false <= MAX_GOOD_FLAGGED, caught, -false, -len(s)))
        best = sets[max(range(len(sets)), key=keys.__getitem__)]
        net, alone = _split_limits(train, ftrain, net_set, best)
        idx = [i for i, r in enumerate(rows) if r["fold"] == k]
        held[idx] = _split_flags([rows[i] for i in idx], net, alone)
        idx = [i for i, r in enumerate(forest_rows) if r["fold"] == k]
        held_alone[idx] = flags([forest_rows[i] for i in idx], alone)
        lines.append(
            f"fold {k}: with_net {net}; forest_alone adds {', '.join(best) or '-'} -> {alone}"
        )
    lines += _rate_lines(rows, held, "nested, shipped rows")
    lines += _rate_lines(forest_rows, held_alone, "nested, forest-alone rows")
    return lines


def nested(rows: list[dict], sets: list[tuple[str, ...]]) -> list[str]:
    """The choice among sets of judged figures, itself cross-validated.

    Outer fold ``k``: each set is cross-validated on the other folds
    (:func:`cross_validate`); the set that catches most of their > 25 % cases
    while flagging at most 25 % of their within-10 % cases (ties: fewer
    within-10 % flagged, then fewer figures) gets its limits chosen on those
    folds and is judged on fold ``k``.
    """
    rows = [r for r in rows if np.isfinite(r["vol_err"])]
    held = np.zeros(len(rows), bool)
    lines = []
    for k in sorted({r["fold"] for r in rows}):
        train = [r for r in rows if r["fold"] != k]
        best = _best_set(train, sets)
        lim = choose(train, best)
        idx = [i for i, r in enumerate(rows) if r["fold"] == k]
        held[idx] = flags([rows[i] for i in idx], lim)
        lines.append(f"fold {k}: {', '.join(best)} -> {lim}")
    real = np.array([r["group"] != "phantom" for r in rows])
    c, f, nb, ng = rates(rows, held)
    rc, rf, rnb, rng = rates([r for r, x in zip(rows, real, strict=True) if x], held[real])
    lines.append(
        f"nested: {c:.0%} of {nb} > 25 % flagged, {f:.0%} of {ng} within 10 %; real cases: "
        f"{rc:.0%} of {rnb}, {rf:.0%} of {rng}"
    )
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", help="learned_cv.py --json rows")
    ap.add_argument(
        "--measures",
        nargs="+",
        choices=sorted(GRID),
        default=None,
        help='the figures judged (default: those of REVIEW_LIMITS["with_net"])',
    )
    ap.add_argument(
        "--forest-alone",
        default=None,
        metavar="ROWS",
        help="the same run's rows without the U-Net: each kind judged by its own limits",
    )
    ap.add_argument(
        "--alone-extra",
        nargs="*",
        choices=sorted(GRID),
        default=None,
        help="with --forest-alone: the forest alone's own figures (default: "
        'those of REVIEW_LIMITS["forest_alone"] that "with_net" lacks)',
    )
    ap.add_argument(
        "--nested-alone",
        nargs="+",
        metavar="A,B,...",
        default=None,
        help="with --forest-alone: choose the forest alone's own figures among these sets "
        "('-': none) inside each fold's choosing folds, judged on the held-out fold (with "
        "--nested: the with_net figures chosen among its sets first, doubly nested)",
    )
    ap.add_argument(
        "--nested",
        nargs="+",
        metavar="A,B,...",
        default=None,
        help="choose among these sets of judged figures by cross-validation inside each "
        "fold's choosing folds, and judge the choice on the held-out fold",
    )
    ap.add_argument(
        "--default-rows",
        default=None,
        metavar="ROWS",
        help="with --forest-alone: learned_cv.py --method auto rows; their T2 cases, where "
        "the default runs another method (robust; paper on the T2 phantoms), are judged by "
        "their status's doubts in place of those cases' learned rows (the review as the "
        "default ships it)",
    )
    ap.add_argument(
        "--bagged",
        type=int,
        default=0,
        metavar="B",
        help="bag each choice of limits over B (odd) bootstrap resamples of the patients: "
        "each figure's limit the median of the chosen grid indices (0: not bagged)",
    )
    args = ap.parse_args(argv)
    if args.bagged < 0 or (args.bagged and args.bagged % 2 == 0):
        ap.error(f"--bagged must be 0 or an odd number of resamples, got {args.bagged}")
    if args.bagged and (args.nested or args.nested_alone):
        ap.error("--bagged does not apply to --nested or --nested-alone")
    if args.default_rows and not args.forest_alone:
        ap.error("--default-rows needs --forest-alone")
    rows = json.loads(Path(args.rows).read_text())
    net_sets = [tuple(s.split(",")) for s in args.nested] if args.nested else None
    alone_sets = [() if s == "-" else tuple(s.split(",")) for s in args.nested_alone or ()]
    bad = sorted({m for s in (net_sets or []) + alone_sets for m in s} - set(GRID))
    if bad:
        ap.error(f"no grid for {bad}: expected among {sorted(GRID)}")
    if args.forest_alone:
        forest = json.loads(Path(args.forest_alone).read_text())
        if alone_sets:
            print("\n".join(nested_alone(rows, forest, alone_sets, net_sets)))
            return 0
        default = None
        if args.default_rows:  # the T2 cases, where the default runs a rule-based method
            default = [
                r
                for r in json.loads(Path(args.default_rows).read_text())
                if r["case"].endswith("/t2")
            ]
        out = cross_validate_split(
            rows, forest, args.measures, args.alone_extra, default, args.bagged
        )
        print("\n".join(out["lines"]))
        return 0
    if net_sets:
        print("\n".join(nested(rows, net_sets)))
        return 0
    out = cross_validate(rows, args.measures, args.bagged)
    print("\n".join(out["lines"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
