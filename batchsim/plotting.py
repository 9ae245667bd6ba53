"""matplotlib for the plots the analysis commands write to files (`--plot`): one place that
loads it on the Agg backend and says which extra brings it where it is missing."""

from __future__ import annotations

from typing import Any

from batchsim.startup import install_command


def pyplot() -> Any:
    """matplotlib.pyplot drawing into files (the Agg backend); RuntimeError, one line, where it is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise RuntimeError(f"--plot needs matplotlib: {install_command('bench')}") from None
    return plt
