"""Report pages: ``report.html`` per patient, ``cohort.html``, and a markdown summary.

Pure string builders from plain dicts: no file is read or written here (the
publishing step writes the strings beside the images they link to). Every
value taken from the input is HTML-escaped; image and page links must be
relative paths inside the output folder (no scheme, no ``..``), and are
URL-quoted. The pages use no JavaScript and no network; the cohort's volume
distribution is an inline SVG.

Patient input (:func:`patient_report_html`, :func:`patient_report_markdown`)
--------------------------------------------------------------------------
A mapping with the keys (all but ``patient_id`` optional)::

    patient_id        str
    status            str: "ok", "check" or "failed" (:mod:`tumor3d.segmentation.review`)
    review_reasons    list of str: why a human should check (status "check")
    tumour_found      bool: False says "No tumour found" first, in words
    measured          str, what the mask (every volume) holds, in words
                      (:func:`tumor3d.segmentation.segment.lesion_definition`)
    volumes_mm3       {"eq7": float, "voxel": float, "mesh": float,
                       "mesh_simplified": float}  (any subset; None = n/a)
    eq7_precision     {"ce": float, "ci95_low_mm3": float, "ci95_high_mm3": float}
                      (the predicted coefficient of error of Eq. 7 and its 95 % interval)
    measurements      {label: value-with-unit str or number}  (e.g. RANO diameters)
    notes             list of str
    n_slices          int
    abnormal_slices   list of int (0-based slice indices)
    slab_height_mm    float
    faces_before      int   (marching cubes)
    faces_after       int   (after simplification)
    stage_seconds     {stage name: seconds}
    stage_cached      {stage name: bool}  (the stage was a cache hit this run)
    slice_counts      {label: int}  (e.g. slices with tumour, slices Eq. 7 summed)
    renders           {view name: relative PNG path}  (e.g. "render_anterior.png")
    turntable         relative GIF path
    overlays          {caption: relative PNG path}  (tumour and brain-mask mosaics)
    viewer            relative path of viewer.html
    provenance        JSON-able dict (shown as JSON)

Cohort input (:func:`cohort_report_html`): a sequence of mappings with
``patient_id``, ``status``, ``volumes_mm3`` (as above), ``notes`` (list of
str: why to check, then the other notes), ``thumbnail`` and ``report``
(relative paths).

The package holds the pages by concept: :mod:`~tumor3d.storage.report_html.fields`
(the values every page shows, escaped and formatted once),
:mod:`~tumor3d.storage.report_html.patient` (``report.html``),
:mod:`~tumor3d.storage.report_html.summary` (the markdown summary and its table) and
:mod:`~tumor3d.storage.report_html.cohort` (``cohort.html``). The public names are
importable from here.
"""

from __future__ import annotations

from tumor3d.storage.report_html.cohort import cohort_report_html
from tumor3d.storage.report_html.fields import EQ7_PRECISION_DEFINITION, VOLUME_DEFINITIONS
from tumor3d.storage.report_html.patient import patient_report_html
from tumor3d.storage.report_html.summary import patient_report_markdown, patient_summary_table

__all__ = [
    "EQ7_PRECISION_DEFINITION",
    "VOLUME_DEFINITIONS",
    "cohort_report_html",
    "patient_report_html",
    "patient_report_markdown",
    "patient_summary_table",
]
