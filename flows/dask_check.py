"""Connect to a Dask scheduler once, in the child process that `check_scheduler` starts.

``python -m tumor3d.flows.dask_check ADDRESS TIMEOUT_S`` prints one JSON line,
``{"workers": N}`` or ``{"error": KIND, "text": FIRST_LINE}``, and ends at once
(``os._exit``: a client half made by a service that is no scheduler would
otherwise wait, and print, at interpreter exit). Imports nothing of tumor3d.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any

__all__ = ["connect_once"]


def connect_once(address: str, timeout_s: float) -> dict[str, Any]:
    """``{"workers": N}``, or ``{"error": KIND, "text": ...}`` (``KIND`` "OSError" for any)."""
    try:
        import distributed

        with distributed.Client(address, timeout=timeout_s, set_as_default=False) as client:
            return {"workers": len(client.scheduler_info().get("workers", {}))}
    except Exception as exc:  # reported as one line by the caller (Ctrl-C stays Ctrl-C)
        kind = "OSError" if isinstance(exc, OSError) else type(exc).__name__
        lines = str(exc).strip().splitlines()
        return {"error": kind, "text": lines[0] if lines else ""}


if __name__ == "__main__":
    print(json.dumps(connect_once(sys.argv[1], float(sys.argv[2]))), flush=True)
    os._exit(0)
