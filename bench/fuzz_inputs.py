"""Fuzzing every node input with 10,000 generated messages each (issue 23).

Runs the generator and the checks of ``tests/fuzz_nodes.py`` (the same as
``tests/test_fuzz_inputs.py``, which runs a few dozen per input) on every subscription of
every node, and counts instead of stopping at the first finding: per input, the examples
run, exceptions that escaped a callback, messages after which NaN or inf was published, and
rejections logged without a count changing. PASS when all three are 0. The first finding of
each kind is printed below the table. Exits with 1 on any FAIL.

Run (after ``bash scripts/bootstrap.sh``)::

    source scripts/env.sh
    python bench/fuzz_inputs.py [--examples 10000] [--only marker_detector,monoslam]
        [--topics camera_info,tf]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))

import rclpy
from fuzz_nodes import NODES, TARGETS, NodeUnderFuzz, fuzzed, sane_others, type_name
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st


def fuzz_one(under: NodeUnderFuzz, topic: str, count: int) -> dict[str, object]:
    """Run ``count`` examples on ``topic``; return the counts and first findings."""
    result: dict[str, object] = {'examples': 0, 'escaped': 0, 'non-finite': 0, 'uncounted': 0}
    message_type = type_name(under.inputs[topic])

    @settings(
        max_examples=count,
        deadline=None,
        database=None,
        phases=(Phase.generate,),
        suppress_health_check=list(HealthCheck),
    )
    @given(data=st.data())
    def run(data: st.DataObject) -> None:
        recipe = data.draw(fuzzed(message_type))
        outcome = under.feed(topic, recipe, sane_others(under, topic, data.draw))
        result['examples'] = int(result['examples']) + 1  # type: ignore[call-overload]
        for kind, finding in (
            ('escaped', outcome.escaped),
            ('non-finite', outcome.non_finite),
            ('uncounted', outcome.uncounted),
        ):
            if finding:
                result[kind] = int(result[kind]) + 1  # type: ignore[call-overload]
                result.setdefault(f'first {kind}', f'{recipe.mutations}: {finding}')

    run()
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--examples', type=int, default=10_000, help='messages per input')
    parser.add_argument(
        '--only', default='', help='only the nodes whose name contains one of these (a,b)'
    )
    parser.add_argument(
        '--topics', default='', help='only the inputs whose topic contains one of these (a,b)'
    )
    args = parser.parse_args()
    rclpy.init()
    rows, details, failed = [], [], False
    try:
        made: dict[str, NodeUnderFuzz] = {}
        for key, topic in TARGETS:
            if not any(part in key for part in args.only.split(',')):
                continue
            if not any(part in topic for part in args.topics.split(',')):
                continue
            if key not in made:
                made[key] = NodeUnderFuzz(NODES[key]())
            started = time.monotonic()
            result = fuzz_one(made[key], topic, args.examples)
            bad = any(result[k] for k in ('escaped', 'non-finite', 'uncounted'))
            failed |= bad
            rows.append(
                f'| {key} | {topic} | {result["examples"]} | {result["escaped"]} | '
                f'{result["non-finite"]} | {result["uncounted"]} | '
                f'{time.monotonic() - started:.0f} | {"FAIL" if bad else "PASS"} |'
            )
            print(rows[-1], flush=True)
            details += [f'- {key} {topic}, {k}: {v}' for k, v in result.items() if 'first' in k]
        for under in made.values():
            under.node.destroy_node()
    finally:
        rclpy.shutdown()
    print()
    print(
        '| node | input | examples | escaped exceptions | non-finite outputs | uncounted '
        'rejections | s | result |'
    )
    print('|---|---|---:|---:|---:|---:|---:|---|')
    print('\n'.join(rows))
    if details:
        print('\nFirst findings:\n' + '\n'.join(d[:2000] for d in details))
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
