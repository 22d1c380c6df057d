"""Where the shared real sequences are, for the benchmarks and the tests: the folder ``$GAUSEM_SHARED_DATA``, by
default ``../shared/data`` beside the checkout. Dataset specs may name it as ``$GAUSEM_SHARED_DATA``."""
from __future__ import annotations

import os
from pathlib import Path

VARIABLE = "GAUSEM_SHARED_DATA"
SHARED_DATA = Path(os.environ.get(VARIABLE, Path(__file__).resolve().parents[3] / "shared" / "data"))


def expand(spec: str) -> str:
    """``spec`` with ``$GAUSEM_SHARED_DATA`` replaced by the shared folder."""
    return spec.replace(f"${VARIABLE}", str(SHARED_DATA))
