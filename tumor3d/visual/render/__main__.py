"""``python -m tumor3d.visual.render``: the Open3D child process (stdin request -> stdout images).

See :func:`tumor3d.visual.render.offscreen._worker_main`.
"""

import os
import sys

from tumor3d.visual.render.offscreen import _worker_main

if __name__ == "__main__":
    _code = _worker_main()
    sys.stderr.flush()
    os._exit(_code)  # skip Filament's teardown: the images are already written
