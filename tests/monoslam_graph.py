"""The monoslam_shadow graph's parameters, for the topic tests that run its nodes as it does."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from graph_checks import graph_node_parameters

from monoslam_shadow_node.feature_tracker.settings import PARAMETERS as TRACKER_PARAMETERS
from monoslam_shadow_node.monoslam.settings import PARAMETERS as MONOSLAM_PARAMETERS
from monoslam_shadow_node.shadow_filter.settings import PARAMETERS as SHADOW_PARAMETERS

ROOT = Path(__file__).resolve().parents[1]
GRAPH = ROOT / 'src' / 'slam_bringup' / 'graphs' / 'monoslam_shadow.yaml'

NODE_PARAMETERS = {
    'feature_tracker': TRACKER_PARAMETERS,
    'monoslam': MONOSLAM_PARAMETERS,
    'shadow_filter': SHADOW_PARAMETERS,
}


def graph_parameters(node: str) -> dict[str, Any]:
    """Return ``node``'s parameters as the graph sets them: the defaults, then its parameter
    files and inline values in order."""
    return graph_node_parameters(GRAPH, node, NODE_PARAMETERS[node])


def tracker_noise(node: str) -> dict[str, Any]:
    """Return the feature tracker's noise as the graph declares it to ``node``."""
    return {'tracking_offset_px': graph_parameters(node)['tracking_offset_px']}
