"""Registry entries named by import string ("package.module:attribute"), imported on first use.

Why: a registry lower in the package (the encoder catalog, the backbone registry) can name an
implementation that lives higher up or pulls in lerobot, without importing it until it is used, so the
import graph stays a DAG and light commands stay light.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any


def import_string(path: str) -> Any:
    """The object "package.module:attribute" names."""
    module, _, attribute = path.partition(":")
    return getattr(import_module(module), attribute)
