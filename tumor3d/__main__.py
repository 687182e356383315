"""``python -m tumor3d``: the command line, as the installed ``tumor3d`` command."""

from tumor3d.flows.daemon import main

if __name__ == "__main__":
    main()
