"""What the analysis commands (`batchsim evaluate`, `resim`, `calibrate`) write beside their
table: `--json FILE` and `--plot FILE`, each said in a line; a plot without matplotlib is one line
naming the extra that brings it (batchsim.plotting), exit 2."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from batchsim.cli.args import UsageError


def write_reports(json_path: Path | None, document: Callable[[], Any], plot_path: Path | None, draw: Callable[[Path], Any]) -> None:
    """`document()` as JSON into `json_path` and `draw(plot_path)`, where given."""
    if json_path is not None:
        json_path.write_text(json.dumps(document(), indent=1))
        print(f"wrote {json_path}")
    if plot_path is not None:
        try:
            draw(plot_path)
        except RuntimeError as e:
            raise UsageError(str(e)) from None
        print(f"wrote {plot_path}")
