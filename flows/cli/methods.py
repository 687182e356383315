"""The ``methods`` command: the registered segmentation methods and input formats."""

from __future__ import annotations

from rich.markup import escape
from rich.table import Table

from tumor3d.flows.cli.app import app, console

#: The tables' widest line, in characters: their descriptions wrap to it in a terminal as
#: wide as a log file's console (:data:`tumor3d.flows.cli.app.PIPED_WIDTH`) alike.
TABLE_WIDTH = 100


@app.command()
def methods() -> None:
    """List the segmentation methods (segment.method) and the input formats (their registries)."""
    from tumor3d.segmentation.methods import AUTO, registered_methods
    from tumor3d.storage.readers.registry import registered_readers

    table = Table(title="Segmentation methods (segment.method)", title_justify="left")
    for col in ("method", "what it is", "modalities"):
        table.add_column(col)
    table.add_row(AUTO, "the default: picks one of the below by modality (see the README)", "")
    for m in sorted(registered_methods().values(), key=lambda m: m.name):
        table.add_row(m.name, escape(m.description), ", ".join(m.modalities))
    width = min(console.width, TABLE_WIDTH)
    console.print(table, width=width)
    formats = Table(title="Input formats", title_justify="left")
    for col in ("reader", "give"):
        formats.add_column(col)
    for r in registered_readers().values():
        formats.add_row(r.name, escape(r.accepts))
    console.print(formats, width=width)
