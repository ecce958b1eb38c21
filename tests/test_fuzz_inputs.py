"""Fuzzing every node input (tests/fuzz_nodes.py): random, extreme and non-finite field values
on each subscription of each node. No exception escapes a callback, no NaN or inf is
published, every rejection logged is counted. SLAM_FUZZ_EXAMPLES sets the examples per input
(bench/fuzz_inputs.py runs 10,000)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fuzz_nodes import (
    INPUTS,
    NODES,
    TARGETS,
    NodeUnderFuzz,
    examples,
    fuzzed,
    sane_others,
    type_name,
)
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

_made: dict[str, NodeUnderFuzz] = {}


@pytest.fixture(scope='module')
def nodes(ros_context: None) -> Iterator[dict[str, NodeUnderFuzz]]:
    yield _made
    for under in _made.values():
        under.node.destroy_node()
    _made.clear()


def node_for(nodes: dict[str, NodeUnderFuzz], key: str) -> NodeUnderFuzz:
    if key not in nodes:
        nodes[key] = NodeUnderFuzz(NODES[key]())
    return nodes[key]


@pytest.mark.parametrize('key', list(INPUTS))
def test_every_input_of_the_node_is_fuzzed(nodes: dict[str, NodeUnderFuzz], key: str) -> None:
    under = node_for(nodes, key)
    assert set(INPUTS[key]) <= set(under.inputs)
    if '(compressed)' not in key:
        assert set(under.inputs) == set(INPUTS[key])


@pytest.mark.parametrize(('key', 'topic'), TARGETS, ids=[f'{k}:{t}' for k, t in TARGETS])
def test_fuzzed_messages_neither_escape_nor_publish_non_finite_nor_go_uncounted(
    nodes: dict[str, NodeUnderFuzz], key: str, topic: str
) -> None:
    under = node_for(nodes, key)
    message_type = type_name(under.inputs[topic])

    @settings(
        max_examples=examples(),
        deadline=None,
        database=None,
        phases=(Phase.generate, Phase.shrink),
        suppress_health_check=list(HealthCheck),
    )
    @given(data=st.data())
    def run(data: st.DataObject) -> None:
        recipe = data.draw(fuzzed(message_type), label='message')
        others = sane_others(under, topic, data.draw)
        outcome = under.feed(topic, recipe, others)
        assert outcome.escaped is None, f'{recipe.mutations}: {outcome.escaped}'
        assert not outcome.non_finite, f'{recipe.mutations}: NaN or inf in {outcome.non_finite}'
        assert not outcome.uncounted, f'{recipe.mutations}: not counted: {outcome.uncounted}'

    run()
