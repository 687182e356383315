"""``python -m tumor3d.flows.cli``: the ``tumor3d`` command."""

from tumor3d.flows.cli import main

main()
