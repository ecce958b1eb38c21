"""PacedGate: the player's rule for paced replay (slam_bringup.pacing)."""

from __future__ import annotations

from slam_bringup.pacing import PacedGate, Shortfall


def report(**counts: int) -> list[tuple[str, str]]:
    """('taken /a', '3')-style pairs from taken_a=3, published_b=2 keywords."""
    pairs = []
    for key, value in counts.items():
        kind, _, topic = key.partition('_')
        pairs.append((f'{kind} /{topic}', str(value)))
    return pairs


def test_expected_nodes_are_missing_until_they_report() -> None:
    gate = PacedGate(['/detector', '/mapper'])
    assert gate.missing() == ['/detector', '/mapper']
    gate.update('/detector', report(taken_image=0))
    assert gate.missing() == ['/mapper']


def test_a_node_behind_the_player_holds_it_up() -> None:
    gate = PacedGate()
    gate.update('/detector', report(taken_image=4, published_fiducials=4))
    assert gate.shortfalls({'/image': 4}) == []
    assert gate.shortfalls({'/image': 5}) == [Shortfall('/detector', '/image', 4, 5)]


def test_a_chain_is_done_only_when_the_last_node_took_what_the_first_published() -> None:
    gate = PacedGate()
    gate.update('/detector', report(taken_image=5, published_fiducials=5))
    gate.update('/mapper', report(taken_fiducials=4))
    assert gate.shortfalls({'/image': 5}) == [Shortfall('/mapper', '/fiducials', 4, 5)]
    gate.update('/mapper', report(taken_fiducials=5))
    assert gate.shortfalls({'/image': 5}) == []


def test_publishers_on_one_topic_add_up() -> None:
    gate = PacedGate()
    gate.update('/a', report(published_tf=3))
    gate.update('/b', report(published_tf=2))
    gate.update('/listener', report(taken_tf=4))
    assert gate.shortfalls({'/tf': 1}) == [Shortfall('/listener', '/tf', 4, 6)]


def test_topics_no_one_counts_never_hold_the_player_up() -> None:
    gate = PacedGate()
    gate.update('/detector', report(taken_tfstatic=7))  # fed by a driver that does not report
    assert gate.shortfalls({'/image': 0}) == []


def test_other_values_are_ignored() -> None:
    gate = PacedGate()
    gate.update('/n', [('taken /a', 'many'), ('busy %', '3.0'), ('taken /b', '2')])
    assert gate.shortfalls({'/a': 9, '/b': 3}) == [Shortfall('/n', '/b', 2, 3)]
    assert str(Shortfall('/n', '/b', 2, 3)) == '/n took 2 of 3 on /b'


def test_the_first_message_waits_until_every_taker_is_matched() -> None:
    gate = PacedGate(['/detector', '/ingest', '/mapper'])
    gate.update('/detector', [('taken /image', '0'), ('subscribers /observations', '1')])
    gate.update('/ingest', report(taken_observations=0, taken_odom=0))
    gate.update('/mapper', report(taken_observations=0))
    assert [str(s) for s in gate.unmatched({'/image': 1, '/odom': 0})] == [
        'the player is matched with 0 of 1 on /odom',
        '/detector is matched with 1 of 2 on /observations',
    ]
    gate.update('/detector', [('taken /image', '0'), ('subscribers /observations', '3')])
    assert gate.unmatched({'/image': 1, '/odom': 1}) == []
