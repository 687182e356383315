"""Size of ``viewer.html`` and of the output folder's shared script (issue 33).

The demo phantom (seed 7, as ``make demo``) is run through the pipeline in
this process (no Prefect), then the page is built as publishing builds it
(:func:`tumor3d.storage.viewer.viewer_html`: the scan cropped to the brain box, the
tumour and brain masks, the simplified tumour and the brain reduced to
:data:`tumor3d.tasks.brain_surface.VIEWER_BRAIN_MAX_FACES` faces). Printed: the page
size and what each embedded part takes, the time to build it, and the
shared ``_assets`` files written once per output folder (NiiVue's script
and licences), against the plotly page each patient carried before
(2.19 MB for this phantom, ``reports/benchmarks.md``).

Usage::

    python benchmarks/bench_viewer.py
"""

from __future__ import annotations

import json
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.flows.patient import run_stages_direct  # noqa: E402
from tumor3d.phantom import make_phantom_patient  # noqa: E402
from tumor3d.storage.phantom_io import write_phantom_patient  # noqa: E402
from tumor3d.storage.store import ArtifactStore  # noqa: E402
from tumor3d.storage.viewer import NIIVUE_VERSION, viewer_assets, viewer_html  # noqa: E402


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        patient = make_phantom_patient(7, patient_id="demo")
        image = write_phantom_patient(patient, Path(tmp) / "in").image
        run = run_stages_direct(image, Path(tmp) / "store", patient_id="demo")
        store = ArtifactStore(Path(tmp) / "store")
        art = {name: out.artifacts for name, out in run.outputs.items()}
        scan, affine = store.get_volume(art["ingest-scan"]["scan"])
        tumour, _ = store.get_volume(art["segment-tumor"]["tumor_mask_slices"])
        brain, _ = store.get_volume(art["preprocess"]["brain_mask"])
        simplified = store.get_mesh(art["simplify-mesh"]["mesh"])
        light = store.get_mesh(art["extract-brain-surface"]["brain_mesh_viewer"])
    t0 = time.perf_counter()
    page = viewer_html(
        scan, affine, tumour, brain_zyx=brain, tumour_mesh=simplified, brain_mesh=light
    )
    build_s = time.perf_counter() - t0
    data = json.loads(re.search(r'id="t3d-data">(.*?)</script>', page, re.S).group(1))
    parts = {
        "MR image (8-bit NIfTI gz, base64)": len(data["image"]),
        "tumour mask": len(data["tumour_mask"]),
        "brain mask": len(data["brain_mask"]),
    }
    for m in data["meshes"]:
        parts[f"{m['name']} (vertices + faces)"] = len(m["vertices"]) + len(m["faces"])
    total = len(page.encode())
    parts["page code and markup"] = total - sum(parts.values())
    print(
        f"demo phantom: scan {scan.shape} (z, y, x); tumour {simplified.n_faces} faces, "
        f"viewer brain {light.n_faces} faces; page built in {build_s:.2f} s"
    )
    print(f"{'viewer.html part':<44}{'bytes':>12}{'MB':>8}")
    for name, n in parts.items():
        print(f"{name:<44}{n:>12,}{n / 1e6:>8.3f}")
    print(f"{'viewer.html (per patient)':<44}{total:>12,}{total / 1e6:>8.3f}")
    for name, blob in viewer_assets().items():
        print(
            f"{'_assets/' + name + ' (once per folder)':<44}{len(blob):>12,}{len(blob) / 1e6:>8.3f}"
        )
    print(f"NiiVue {NIIVUE_VERSION}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
