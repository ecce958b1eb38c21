"""scipy.stats chi2, ncx2, norm and t, imported on first use (docs/design/ros_and_core.md)."""

from __future__ import annotations

import importlib
from typing import Any


class _LazyDistribution:
    """Forwards attribute lookups to ``scipy.stats.<name>``."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attribute: str) -> Any:
        distribution = getattr(importlib.import_module('scipy.stats'), self._name)
        return getattr(distribution, attribute)

    def __repr__(self) -> str:
        return f'<scipy.stats.{self._name}, imported on first use>'


chi2: Any = _LazyDistribution('chi2')
ncx2: Any = _LazyDistribution('ncx2')
norm: Any = _LazyDistribution('norm')
t: Any = _LazyDistribution('t')


def load() -> None:
    """Import scipy.stats and scipy.optimize now: a node calls it before it subscribes."""
    importlib.import_module('scipy.stats')
    importlib.import_module('scipy.optimize')
