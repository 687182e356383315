"""A self-contained interactive 3-D viewer page (``viewer.html``) of the tumour and brain.

:func:`viewer_html` returns one HTML document with plotly.js embedded: it
opens from disk with no network. By default plotly.js travels
gzip-compressed and base64-encoded in the page and the browser unpacks it
with ``DecompressionStream`` before drawing (a browser without it, older
than Chrome/Edge 80, Firefox 113 or Safari 16.4, shows a message saying so);
``compress_plotlyjs=False`` embeds it as plain script.
The tumour (opaque) and the brain (translucent) are two ``Mesh3d`` traces in
RAS millimetres; drag rotates, the wheel zooms, clicking a legend entry
(or the buttons above the plot) shows or hides a surface. Axes are labelled
with their anatomical directions and drawn at equal scale
(``aspectmode="data"``). The same meshes give the same bytes (fixed div id,
no timestamps).

Size: plotly.js is 4.82 MB as plain script and 1.96 MB compressed (plotly
7.1); the meshes travel as base64 typed arrays (float32 vertices, uint16
face indices when the mesh has at most 65,536 vertices). The pipeline gives
the viewer the simplified tumour and the brain reduced to 8,000 faces
(``tasks/brain_surface.py``): 2.19 MB for the demo phantom, against 5.88 MB
with plain plotly.js, the full 37,596-face brain and int32 indices
(``benchmarks/bench_viewer.py``, ``reports/benchmarks.md``).

Shading uses plotly's own Phong-like ``lighting`` (ambient, diffuse,
specular, roughness) with the light at the camera, close to the offscreen
renders of :mod:`tumor3d.render`.
"""

from __future__ import annotations

import base64
import functools
import gzip
import html
from collections.abc import Sequence

import numpy as np

from tumor3d.errors import InputError
from tumor3d.mesh import Mesh

__all__ = ["viewer_html"]

_DIV_ID = "tumor3d-viewer"


def _rgb_css(rgb: Sequence[float], name: str) -> str:
    arr = np.asarray(rgb, dtype=np.float64)
    if arr.shape != (3,) or not np.all((arr >= 0) & (arr <= 1)):
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {rgb!r}")
    r, g, b = (int(round(255 * c)) for c in arr)
    return f"rgb({r},{g},{b})"


def _index_dtype(n_vertices: int) -> type:
    """The smallest unsigned type that holds every vertex index."""
    return np.uint16 if n_vertices <= 65536 else np.uint32


def _trace(mesh: Mesh, name: str, color: str, opacity: float, decimals: int):  # noqa: ANN202
    import plotly.graph_objects as go

    v = np.round(mesh.vertices, decimals).astype(np.float32)
    # plotly encodes arrays as base64 typed arrays of their own dtype: the
    # smallest index type that fits halves the face data of most meshes
    f = mesh.faces.astype(_index_dtype(mesh.n_vertices))
    return go.Mesh3d(
        x=v[:, 0],
        y=v[:, 1],
        z=v[:, 2],
        i=f[:, 0],
        j=f[:, 1],
        k=f[:, 2],
        name=name,
        color=color,
        opacity=opacity,
        flatshading=False,
        showlegend=True,
        hoverinfo="name",
        lighting={"ambient": 0.35, "diffuse": 0.7, "specular": 0.3, "roughness": 0.5},
        lightposition={"x": 0, "y": 1e5, "z": 0},
    )


def viewer_html(
    tumor: Mesh,
    brain: Mesh | None = None,
    *,
    title: str = "tumor3d viewer",
    tumor_color_rgb: Sequence[float] = (0.85, 0.35, 0.3),
    brain_color_rgb: Sequence[float] = (0.78, 0.78, 0.82),
    brain_opacity: float = 0.25,
    decimals: int = 2,
    compress_plotlyjs: bool = True,
) -> str:
    """The interactive viewer page as an HTML string.

    Parameters
    ----------
    tumor : Mesh
        Non-empty tumour surface, RAS mm.
    brain : Mesh, optional
        Brain surface in the same frame, drawn translucent.
    title : str
        Page and plot title (HTML-escaped).
    tumor_color_rgb, brain_color_rgb : sequence of 3 float
        Colours, components in [0, 1].
    brain_opacity : float
        Brain opacity in (0, 1].
    decimals : int
        Vertex coordinates are rounded to this many decimals of a mm (0-6)
        to keep the page small.
    compress_plotlyjs : bool
        Embed plotly.js gzip-compressed (1.96 MB of base64 instead of 4.82 MB),
        unpacked in the browser with ``DecompressionStream`` (Chrome/Edge 80+,
        Firefox 113+, Safari 16.4+; an older browser shows a message saying
        so instead of the plot). ``False`` embeds it as plain script, readable
        by any browser.

    Returns
    -------
    str
        A complete HTML document (UTF-8 text) with plotly.js embedded.

    Raises
    ------
    InputError
        On an empty or non-mesh input or a bad parameter.
    """
    import plotly.graph_objects as go
    import plotly.io as pio

    for mesh, name in ((tumor, "tumor"), (brain, "brain")):
        if name == "brain" and mesh is None:
            continue
        if not isinstance(mesh, Mesh):
            raise InputError(f"{name} must be a tumor3d.mesh.Mesh, got {type(mesh).__name__}")
        if mesh.is_empty:
            raise InputError(f"the {name} mesh is empty: nothing to view")
    if not isinstance(title, str):
        raise InputError(f"title must be a string, got {type(title).__name__}")
    if (
        isinstance(brain_opacity, bool)
        or not isinstance(brain_opacity, (int, float))
        or not (0.0 < brain_opacity <= 1.0)
    ):
        raise InputError(f"brain_opacity must lie in (0, 1], got {brain_opacity!r}")
    if isinstance(decimals, bool) or not isinstance(decimals, int) or not 0 <= decimals <= 6:
        raise InputError(f"decimals must be an integer in [0, 6], got {decimals!r}")
    traces = [_trace(tumor, "tumour", _rgb_css(tumor_color_rgb, "tumor_color_rgb"), 1.0, decimals)]
    if brain is not None:
        traces.append(
            _trace(
                brain,
                "brain",
                _rgb_css(brain_color_rgb, "brain_color_rgb"),
                float(brain_opacity),
                decimals,
            )
        )
    fig = go.Figure(traces)
    buttons = [
        {"label": "tumour + brain", "method": "restyle", "args": ["visible", [True, True]]},
        {"label": "tumour only", "method": "restyle", "args": ["visible", [True, False]]},
        {"label": "brain only", "method": "restyle", "args": ["visible", [False, True]]},
    ]
    axis = {"showbackground": False, "gridcolor": "#ddd", "zerolinecolor": "#bbb"}
    fig.update_layout(
        title={"text": html.escape(title)},
        template="plotly_white",
        margin={"l": 0, "r": 0, "t": 60, "b": 0},
        legend={"itemclick": "toggle", "x": 0.01, "y": 0.95},
        scene={
            "aspectmode": "data",
            "xaxis": {**axis, "title": {"text": "L  ← x (mm) →  R"}},
            "yaxis": {**axis, "title": {"text": "P  ← y (mm) →  A"}},
            "zaxis": {**axis, "title": {"text": "I  ← z (mm) →  S"}},
            # anterior view, slightly from above: the patient's right on the left
            "camera": {"eye": {"x": 0.0, "y": 2.0, "z": 0.6}, "up": {"x": 0, "y": 0, "z": 1}},
        },
        updatemenus=(
            [
                {
                    "type": "buttons",
                    "direction": "right",
                    "x": 0.99,
                    "xanchor": "right",
                    "y": 1.08,
                    "buttons": buttons,
                }
            ]
            if brain is not None
            else []
        ),
    )
    if not isinstance(compress_plotlyjs, bool):
        raise InputError(f"compress_plotlyjs must be True or False, got {compress_plotlyjs!r}")
    page = pio.to_html(
        fig,
        include_plotlyjs=not compress_plotlyjs,
        full_html=True,
        div_id=_DIV_ID,
        config={"displaylogo": False, "responsive": True},
        default_width="100%",
        default_height="95vh",
    )
    page = page.replace("<head>", f"<head>\n    <title>{html.escape(title)}</title>", 1)
    if compress_plotlyjs:
        page = _with_packed_plotlyjs(page)
    return page


#: Unpacks the gzip-compressed plotly.js embedded in the page, then runs the figure script.
_LOADER = """<script>(function(){
var fig=document.getElementById('t3d-figure'),div=document.getElementById('%(div)s');
if(typeof DecompressionStream==='undefined'||typeof Response==='undefined'){
div.textContent='This browser cannot unpack the embedded 3-D viewer (it needs '+
'DecompressionStream: Chrome or Edge 80+, Firefox 113+, Safari 16.4+).';return;}
var bin=atob(document.getElementById('t3d-plotlyjs').textContent.replace(/\\s+/g,''));
var bytes=new Uint8Array(bin.length);for(var i=0;i<bin.length;i++){bytes[i]=bin.charCodeAt(i);}
new Response(new Blob([bytes]).stream().pipeThrough(new DecompressionStream('gzip'))).text()
.then(function(code){var lib=document.createElement('script');lib.text=code;
document.head.appendChild(lib);var run=document.createElement('script');
run.text=fig.textContent;document.body.appendChild(run);})
.catch(function(e){console.error('tumor3d viewer: cannot unpack plotly.js: '+e);});
})();</script>"""


@functools.cache
def _packed_plotlyjs() -> str:
    """plotly.js, gzip-compressed (no timestamp: the same bytes every time), base64."""
    from plotly.offline import get_plotlyjs

    packed = gzip.compress(get_plotlyjs().encode("utf-8"), compresslevel=9, mtime=0)
    return base64.b64encode(packed).decode("ascii")


def _with_packed_plotlyjs(page: str) -> str:
    """The page with plotly.js embedded compressed, the figure drawn once it is unpacked."""
    start = page.index("<script", page.index(f'id="{_DIV_ID}"'))
    end = page.index(">", start) + 1
    figure = '<script type="text/plain" id="t3d-figure">'
    lib = f'<script type="application/octet-stream" id="t3d-plotlyjs">{_packed_plotlyjs()}</script>'
    page = page[:start] + figure + page[end:]
    close = page.rindex("</body>")
    return page[:close] + lib + (_LOADER % {"div": _DIV_ID}) + page[close:]
