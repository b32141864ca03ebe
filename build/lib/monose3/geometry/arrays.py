"""One choice the element-wise geometry makes for every input: numpy or torch."""

from __future__ import annotations

import sys
from types import ModuleType

import numpy as np


def array_module(x: object) -> ModuleType:
    """``torch`` for a tensor, else ``numpy`` (without importing torch when it is not loaded)."""
    if type(x).__module__.startswith("torch"):
        return sys.modules["torch"]
    return np
