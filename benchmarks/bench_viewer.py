"""Size of ``viewer.html``: what plotly.js, the tumour and the brain each take.

The demo phantom (seed 7, as ``make demo``) is run through the pipeline in
this process (no Prefect); its simplified tumour and brain surface are put
into the viewer in four ways:

* ``full brain, int32 faces``: the brain surface as rendered, face indices
  int32 (the viewer before issue 10's size work);
* ``full brain``: the same with the smallest index type (uint16 below
  65,536 vertices), as :func:`storage.viewer.viewer_html` now does;
* ``viewer brain``: the brain reduced to
  :data:`tasks.brain_surface.VIEWER_BRAIN_MAX_FACES` faces (what the
  pipeline publishes);
* ``tumour only`` and an empty plotly page (plotly.js alone), all with
  plotly.js embedded as plain script;
* ``viewer brain, plotly.js gzip``: what the pipeline publishes, plotly.js
  embedded gzip-compressed and unpacked by the browser.

Also reported: the time to reduce the brain (once per brain mask, in the
extract-brain-surface stage) and what int16-quantised vertex coordinates
would still save (not done: plotly would show the axes in quantisation
units).

Usage::

    python benchmarks/bench_viewer.py
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from flows.patient import run_stages_direct  # noqa: E402
from storage.phantom_io import write_phantom_patient  # noqa: E402
from storage.store import ArtifactStore  # noqa: E402
from storage.viewer import viewer_html  # noqa: E402
from tasks.brain_surface import VIEWER_BRAIN_MAX_FACES  # noqa: E402
from tumor3d.brain_surface import display_mesh  # noqa: E402
from tumor3d.phantom import make_phantom_patient  # noqa: E402


def main() -> int:
    import plotly
    import plotly.graph_objects as go
    import plotly.io as pio

    import storage.viewer as viewer_mod

    with tempfile.TemporaryDirectory() as tmp:
        patient = make_phantom_patient(7, patient_id="demo")
        image = write_phantom_patient(patient, Path(tmp) / "in").image
        run = run_stages_direct(image, Path(tmp) / "store", patient_id="demo")
        store = ArtifactStore(Path(tmp) / "store")
        tumour = store.get_mesh(run.outputs["simplify-mesh"].artifacts["mesh"])
        brain = store.get_mesh(run.outputs["extract-brain-surface"].artifacts["brain_mesh"])
    t0 = time.perf_counter()
    light = display_mesh(brain, VIEWER_BRAIN_MAX_FACES)
    reduce_s = time.perf_counter() - t0

    plotly_only = len(pio.to_html(go.Figure(), include_plotlyjs=True, full_html=True).encode())
    sizes = {}

    def size(t, b, *, int32=False, compress=False):
        if not int32:
            return len(viewer_html(t, b, compress_plotlyjs=compress).encode())
        saved = viewer_mod._index_dtype
        viewer_mod._index_dtype = lambda n: np.int32  # the earlier face indices
        try:
            return len(viewer_html(t, b, compress_plotlyjs=False).encode())
        finally:
            viewer_mod._index_dtype = saved

    sizes["full brain, int32 faces"] = size(tumour, brain, int32=True)
    sizes["full brain"] = size(tumour, brain)
    sizes["viewer brain"] = size(tumour, light)
    sizes["tumour only"] = size(tumour, None)
    sizes["plotly.js alone (empty figure)"] = plotly_only
    sizes["viewer brain, plotly.js gzip (published)"] = size(tumour, light, compress=True)
    print(
        f"plotly {plotly.__version__}; tumour {tumour.n_faces} faces / {tumour.n_vertices} "
        f"vertices; brain {brain.n_faces} faces, viewer brain {light.n_faces} faces "
        f"(reduced in {reduce_s:.2f} s)"
    )
    ref = sizes["viewer brain, plotly.js gzip (published)"]
    print(f"{'page':<44}{'bytes':>12}{'MB':>8}{'vs published':>14}")
    for name, n in sizes.items():
        print(f"{name:<44}{n:>12,}{n / 1e6:>8.2f}{n / ref:>14.3f}")
    n_v = tumour.n_vertices + light.n_vertices
    saved = n_v * 3 * 2 * 4 / 3  # float32 -> int16, base64
    print(f"int16 vertex coordinates would save a further {saved / 1e3:.0f} kB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
