"""``shadow_evaluate --sequence DIR``: the Shadow filter over an on-disk sequence.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC, STATUS_NAMES
from monoslam_shadow_node.shadow_filter.core.shadow_filter import ShadowConfig
from slam_evaluation.sequence_files import Sequence
from slam_evaluation.shadow_runs import FilterInput, run_frames


def evaluate_sequence(sequence: Sequence, config: ShadowConfig, name: str) -> dict[str, Any]:
    """Run the Shadow filter over the sequence (known poses); return the report."""
    known = np.array(sorted(sequence.known_points or {}), dtype=np.int64)
    inputs: list[FilterInput] = []
    for index, (ids, pixels) in enumerate(sequence.by_frame()):
        stamp_ns = sequence.stamps_ns[index]
        feature = ~np.isin(ids, known)
        inputs.append(
            (int(stamp_ns), ids[feature], pixels[feature], sequence.rotations[index],
             sequence.centres[index])
        )  # fmt: skip
    record = run_frames(sequence.camera, inputs, config, name)
    tracks = sorted({int(i) for i in sequence.ids.tolist()} - set(known.tolist()))
    final = {
        i: record.decisions[i][1].status if i in record.decisions else PENDING for i in tracks
    }
    without_fit = sum(
        d.status == DYNAMIC and math.isnan(d.statistic) for _, d in record.decisions.values()
    )
    content: dict[str, Any] = {
        'sequence': name,
        'frames': len(inputs),
        'tracks': len(tracks),
        'decided': {
            STATUS_NAMES[s]: sum(v == s for v in final.values()) for s in (STATIC, DYNAMIC)
        },
        'dynamic_without_fit': without_fit,
        'handovers': len(record.handovers),
        'frames_to_decide_median': _median(
            [d.frames_since_first for _, d in record.decisions.values()]
        ),
        'filter_ms_per_frame': 1e3 * record.runtime_s / max(len(inputs), 1),
    }
    if sequence.labels is not None:
        table: Counter[tuple[str, str]] = Counter(
            ('moving' if sequence.labels.get(i, False) else 'static', STATUS_NAMES[s])
            for i, s in final.items()
        )
        content['confusion'] = {
            truth: {
                STATUS_NAMES[s]: table[truth, STATUS_NAMES[s]] for s in (STATIC, DYNAMIC, PENDING)
            }
            for truth in ('static', 'moving')
        }
        static = content['confusion']['static']
        decided = static[STATUS_NAMES[STATIC]] + static[STATUS_NAMES[DYNAMIC]]
        content['static_called_dynamic_of_decided'] = (
            static[STATUS_NAMES[DYNAMIC]] / decided if decided else math.nan
        )
        content['moving_called_static'] = content['confusion']['moving'][STATUS_NAMES[STATIC]]
    return content


def sequence_summary(content: dict[str, Any]) -> str:
    """Return the printed summary of ``evaluate_sequence``'s report."""
    decided = content['decided']
    lines = [
        f'Shadow filter on sequence {content["sequence"]}: {content["frames"]} frames, '
        f'{content["tracks"]} tracks, known poses',
        f'  decided: {", ".join(f"{k} {v}" for k, v in decided.items())} (DYNAMIC because the '
        f'views fix no static point: {content["dynamic_without_fit"]}); '
        f'{content["handovers"]} handovers; frames to decide, median '
        f'{content["frames_to_decide_median"]:.0f}',
    ]
    if 'confusion' in content:
        lines.append('  truth x final status:')
        for truth, row in content['confusion'].items():
            lines.append(f'    {truth:7s}' + ''.join(f' {k} {v:5d}' for k, v in row.items()))
        share = content['static_called_dynamic_of_decided']
        lines.append(
            f'  static called DYNAMIC: {100 * share:.1f} % of decided; moving called STATIC: '
            f'{content["moving_called_static"]}'
        )
    lines.append(f'  filter {content["filter_ms_per_frame"]:.2f} ms/frame')
    return '\n'.join(lines)


def _median(values: list[int]) -> float:
    return float(np.median(values)) if values else math.nan
