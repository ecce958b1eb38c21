"""A node that computes with scipy.stats has imported it before it subscribes. The import
takes about 1 s (6 s on a busy machine); paid at the first use, it stalled monoslam on its
third frame while its 30 Hz inputs overflowed their queues."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
from test_node_parameter_contracts import NODES as EVERY_NODE

SCRIPT = """
import importlib, sys
import rclpy
from rclpy.node import Node

module = importlib.import_module(sys.argv[1])
loaded = []
create_subscription = Node.create_subscription


def spy(self, *args, **kwargs):
    loaded.append('scipy.stats' in sys.modules and 'scipy.optimize' in sys.modules)
    return create_subscription(self, *args, **kwargs)


Node.create_subscription = spy
rclpy.init()
node = getattr(module, sys.argv[2])()
print('subscriptions', len(loaded), 'loaded before each', all(loaded))
node.destroy_node()
rclpy.shutdown()
"""

NODES = [
    ('monoslam_shadow_node.monoslam.node', 'MonoSlamNode'),
    ('monoslam_shadow_node.shadow_filter.node', 'ShadowFilterNode'),
    ('em_sam_node.mapper.node', 'EmSamMapperNode'),
]


@pytest.mark.parametrize(('module', 'node_class'), NODES)
def test_scipy_stats_is_imported_before_the_first_subscription(
    module: str, node_class: str, tmp_path: Path
) -> None:
    done = subprocess.run(
        [sys.executable, '-c', SCRIPT, module, node_class],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    line = done.stdout.strip().splitlines()[-1]
    count = int(line.split()[1])
    assert count > 0 and line.endswith('loaded before each True'), done.stdout


PROBE = (
    'import importlib, sys; importlib.import_module(sys.argv[1]); '
    "print('slam_core.lazy_stats' in sys.modules)"
)


def test_every_node_that_imports_lazy_stats_loads_it() -> None:
    """The test above builds three nodes; label_gate needs a mask file, so its source is read."""
    probes = {
        case.module: subprocess.Popen(
            [sys.executable, '-c', PROBE, case.module], stdout=subprocess.PIPE, text=True
        )
        for case in EVERY_NODE
    }
    answers = {module: p.communicate(timeout=120)[0].strip() for module, p in probes.items()}
    failed = {module: probe.returncode for module, probe in probes.items() if probe.returncode}
    assert not failed, failed  # a module that cannot be imported must not pass unseen
    using = {module for module, answer in answers.items() if answer == 'True'}
    assert {module for module, _ in NODES} <= using
    calling = {module for module in using if 'lazy_stats.load()' in _source(module)}
    assert using == calling, sorted(using - calling)


def _source(module: str) -> str:
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin is not None, module
    return Path(spec.origin).read_text()
