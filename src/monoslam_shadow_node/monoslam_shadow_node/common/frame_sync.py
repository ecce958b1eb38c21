"""Pairing two input streams by stamp, handed out in stamp order (ROS-free).

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

from monoslam_shadow_node.common.core.inputs import CameraPose, Features


class Stamped(Protocol):
    """Anything with an image stamp (int ns)."""

    @property
    def stamp_ns(self) -> int: ...


P = TypeVar('P', bound=Stamped)
Q = TypeVar('Q', bound=Stamped)


@dataclass(frozen=True)
class Drop:
    """An input let go: ``kind``, ``stamp_ns`` (int ns) and the log ``text`` naming it."""

    kind: str
    stamp_ns: int
    text: str

    def __str__(self) -> str:
        return self.text


@dataclass(frozen=True)
class SyncNames:
    """How log lines name the two streams and the drop kinds of an unpaired item."""

    primary: str
    primary_plural: str
    primary_short: str
    partner: str
    partner_plural: str
    partner_topic: str
    missing_partner_kind: str
    missing_primary_kind: str


class StampSync(Generic[P, Q]):
    """Pairs primary items with partner items by stamp (module docstring)."""

    def __init__(
        self,
        *,
        tolerance_ns: int,
        horizon_ns: int,
        max_entries: int,
        names: SyncNames,
        in_order_partners: bool = False,
        stall_ns: int | None = None,
    ) -> None:
        self.in_order_partners = in_order_partners
        self.stall_ns = stall_ns
        self._newest_partner_ns: int | None = None
        # the newest primary stamp when the latest partner came (or the first primary after it)
        self._primary_at_partner_ns: int | None = None
        self._newest_primary_ns: int | None = None
        # in_order_partners: the newest partner stamp when each waiting primary came
        self._partner_at_arrival: dict[int, int | None] = {}
        self.tolerance_ns = tolerance_ns
        self.horizon_ns = horizon_ns
        self.max_entries = max_entries
        self.names = names
        self._primaries: list[P] = []  # sorted by stamp
        self._partners: list[Q] = []  # sorted by stamp
        self._newest_ns: int | None = None
        self._last_ns: int | None = None
        self._seen_ns: deque[int] = deque(maxlen=max_entries)
        self._out_of_order_ns: deque[int] = deque(maxlen=max_entries)

    @property
    def waiting_primaries(self) -> int:
        """Primary items waiting for a partner or for the caller."""
        return len(self._primaries)

    @property
    def waiting_partners(self) -> int:
        """Partner items waiting for their primary."""
        return len(self._partners)

    @property
    def last_ns(self) -> int | None:
        """Stamp (int ns) of the primary handed out last, None before the first."""
        return self._last_ns

    def start_after(self, stamp_ns: int) -> None:
        """Take ``stamp_ns`` as processed last (a resume): earlier primaries are refused."""
        self._last_ns = stamp_ns

    def add_primary(self, item: P) -> list[Drop]:
        """Queue a primary item; return drops (a repeated stamp, a full queue)."""
        names = self.names
        stamp_ns = item.stamp_ns
        stamps = [p.stamp_ns for p in self._primaries]
        if stamp_ns in stamps:
            where = f'{names.primary} at stamp {stamp_ns} ns'
            return [Drop('repeated', stamp_ns, f'{where} dropped: one with this stamp is waiting')]
        self._primaries.insert(bisect.bisect(stamps, stamp_ns), item)
        self._partner_at_arrival[stamp_ns] = self._newest_partner_ns
        if len(self._partner_at_arrival) > 2 * self.max_entries + 2:  # forget those handed out
            waiting = {p.stamp_ns for p in self._primaries}
            self._partner_at_arrival = {
                k: v for k, v in self._partner_at_arrival.items() if k in waiting
            }
        self._seen_ns.append(stamp_ns)
        self._see(stamp_ns)
        if self._newest_primary_ns is None or stamp_ns > self._newest_primary_ns:
            self._newest_primary_ns = stamp_ns
        if self._primary_at_partner_ns is None and self._newest_partner_ns is not None:
            self._primary_at_partner_ns = stamp_ns
        drops = []
        while len(self._primaries) > self.max_entries:
            oldest = self._primaries.pop(0).stamp_ns
            text = (
                f'{names.primary} at stamp {oldest} ns dropped: queue_size={self.max_entries} '
                f'{names.primary_plural} are waiting already'
            )
            drops.append(Drop('overflow', oldest, text))
        return drops

    def add_partner(self, item: Q) -> list[Drop]:
        """Queue a partner item; return drops (a repeated stamp, a full queue)."""
        names = self.names
        stamp_ns = item.stamp_ns
        stamps = [p.stamp_ns for p in self._partners]
        where = f'{names.partner} at stamp {stamp_ns} ns on {names.partner_topic}'
        if stamp_ns in stamps:
            return [Drop('repeated', stamp_ns, f'{where} dropped: one with this stamp is waiting')]
        self._partners.insert(bisect.bisect(stamps, stamp_ns), item)
        self._see(stamp_ns)
        if self._newest_partner_ns is None or stamp_ns > self._newest_partner_ns:
            self._newest_partner_ns = stamp_ns
        self._primary_at_partner_ns = self._newest_primary_ns
        drops = []
        while len(self._partners) > self.max_entries:
            oldest = self._partners.pop(0).stamp_ns
            text = (
                f'{names.partner} at stamp {oldest} ns on {names.partner_topic} dropped: '
                f'queue_size={self.max_entries} {names.partner_plural} are waiting already'
            )
            drops.append(Drop('overflow', oldest, text))
        return drops

    def pop(
        self, *, hold: bool = False, flush: bool = False, alone: bool = False
    ) -> tuple[list[tuple[P, Q | None]], list[Drop]]:
        """Return the pairs ready in stamp order and the drops (``hold``, ``flush``, ``alone``)."""
        pairs: list[tuple[P, Q | None]] = []
        drops: list[Drop] = []
        while self._primaries:
            stamp_ns = self._primaries[0].stamp_ns
            match = self._match(stamp_ns)
            if match is not None:
                if hold:
                    break
                pairs.append((self._primaries.pop(0), self._partners.pop(match)))
                self._handed_out(stamp_ns)
                continue
            if self._last_ns is not None and stamp_ns <= self._last_ns:
                self._out_of_order_ns.append(stamp_ns)
                text = (
                    f'{self.names.primary} at stamp {stamp_ns} ns dropped: not after the frame '
                    f'processed last ({self._last_ns} ns); frames must come in stamp order'
                )
                drops.append(Drop('out_of_order', stamp_ns, text))
            elif flush or self._primary_expired(stamp_ns):
                if alone and not hold:
                    pairs.append((self._primaries.pop(0), None))
                    self._handed_out(stamp_ns)
                    continue
                drops.append(self._missing_partner(stamp_ns))
            else:
                break
            self._primaries.pop(0)
        return pairs, drops + self._drop_stale_partners()

    def missing_reason(self, stamp_ns: int) -> str:
        """Why the primary at ``stamp_ns`` goes without its partner, as the end of a sentence."""
        horizon = f'sync_horizon_s ({self.horizon_ns / 1e9:g} s)'
        if self._passed(stamp_ns):
            return f'before a later one (stamp {self._newest_partner_ns} ns)'
        if self._stalled():
            return (
                f'while {self.names.primary_plural} came for {horizon} of stamps after the last '
                f'(stamp {self._newest_partner_ns} ns)'
            )
        if self._expired(stamp_ns):
            return f'within {horizon}'
        return 'before the inputs stopped'

    def _missing_partner(self, stamp_ns: int) -> Drop:
        names = self.names
        text = (
            f'{names.primary} at stamp {stamp_ns} ns dropped: no {names.partner} with its '
            f'stamp came on {names.partner_topic} {self.missing_reason(stamp_ns)}'
        )
        return Drop(names.missing_partner_kind, stamp_ns, text)

    def _handed_out(self, stamp_ns: int) -> None:
        if self._last_ns is None or stamp_ns > self._last_ns:
            self._last_ns = stamp_ns

    def _see(self, stamp_ns: int) -> None:
        if self._newest_ns is None or stamp_ns > self._newest_ns:
            self._newest_ns = stamp_ns

    def _ahead(self, partner_ns: int | None, stamp_ns: int) -> bool:
        return partner_ns is not None and partner_ns > stamp_ns + self.tolerance_ns

    def _passed(self, stamp_ns: int) -> bool:
        """in_order_partners: a partner later than this waiting primary came after it."""
        return (
            self.in_order_partners
            and self._ahead(self._newest_partner_ns, stamp_ns)
            and not self._ahead(self._partner_at_arrival.get(stamp_ns), stamp_ns)
        )

    def _primary_expired(self, stamp_ns: int) -> bool:
        """Whether a primary still without its partner will not get one (module docstring)."""
        if not self.in_order_partners or self._newest_partner_ns is None:
            return self._expired(stamp_ns)
        if self._ahead(self._partner_at_arrival.get(stamp_ns), stamp_ns):
            return self._expired(stamp_ns)  # it came after a later partner
        return self._passed(stamp_ns) or (self._stalled() and self._expired(stamp_ns))

    def _partner_stale(self, stamp_ns: int) -> bool:
        """Whether a partner no waiting primary matches will not get one (module docstring)."""
        later_primary = self._ahead(self._newest_primary_ns, stamp_ns)
        return self._expired(stamp_ns) and (later_primary or not self.in_order_partners)

    def _stalled(self) -> bool:
        """in_order_partners with stall_ns: the primaries went on that far with no partner."""
        if not self.in_order_partners or self.stall_ns is None:
            return False
        mark, newest = self._primary_at_partner_ns, self._newest_primary_ns
        return mark is not None and newest is not None and newest - mark > self.stall_ns

    def _expired(self, stamp_ns: int) -> bool:
        return self._newest_ns is not None and stamp_ns < self._newest_ns - self.horizon_ns

    def _match(self, stamp_ns: int) -> int | None:
        """Index of the waiting partner nearest to ``stamp_ns`` within the tolerance."""
        best, best_gap = None, self.tolerance_ns
        for index, partner in enumerate(self._partners):
            gap = abs(partner.stamp_ns - stamp_ns)
            if gap <= best_gap:
                best, best_gap = index, gap
        return best

    def _near(self, stamp_ns: int, stamps: Iterable[int]) -> bool:
        return any(abs(s - stamp_ns) <= self.tolerance_ns for s in stamps)

    def _drop_stale_partners(self) -> list[Drop]:
        names = self.names
        drops, kept = [], []
        waiting = [p.stamp_ns for p in self._primaries]
        for partner in self._partners:
            if self._near(partner.stamp_ns, waiting) or not self._partner_stale(partner.stamp_ns):
                kept.append(partner)
            elif not self._near(partner.stamp_ns, self._out_of_order_ns):  # else: said already
                where = f'{names.partner} at stamp {partner.stamp_ns} ns on {names.partner_topic}'
                if self._near(partner.stamp_ns, self._seen_ns):
                    text = f'{where} came after its {names.primary} had gone without it; dropped'
                else:
                    hint = self._nearest_hint(partner.stamp_ns)
                    text = f'{where} matches no {names.primary}{hint}; dropped'
                drops.append(Drop(names.missing_primary_kind, partner.stamp_ns, text))
        self._partners = kept
        return drops

    def _nearest_hint(self, stamp_ns: int) -> str:
        if not self._seen_ns:
            return ' (none seen yet)'
        nearest = min(self._seen_ns, key=lambda s: abs(s - stamp_ns))
        return (
            f' (nearest {self.names.primary_short} stamp {nearest} ns, '
            f'{(nearest - stamp_ns) / 1e6:+.3f} ms away; stamp_tolerance_s is '
            f'{self.tolerance_ns / 1e9:g} s)'
        )


def features_and_poses(pose_topic: str) -> SyncNames:
    """Return the shadow_filter's stream names: feature frames paired with camera poses."""
    return SyncNames(
        primary='features frame',
        primary_plural='frames',
        primary_short='features',
        partner='camera pose',
        partner_plural='poses',
        partner_topic=pose_topic,
        missing_partner_kind='no_pose',
        missing_primary_kind='no_features',
    )


class FrameSynchronizer:
    """Pairs feature frames with camera poses by stamp (``in_order_partners``)."""

    def __init__(
        self, *, tolerance_ns: int, horizon_ns: int, max_entries: int, pose_topic: str
    ) -> None:
        self._sync: StampSync[Features, CameraPose] = StampSync(
            tolerance_ns=tolerance_ns,
            horizon_ns=horizon_ns,
            max_entries=max_entries,
            names=features_and_poses(pose_topic),
            in_order_partners=True,
        )

    @property
    def waiting_features(self) -> int:
        """Feature frames waiting for a pose or for the camera."""
        return self._sync.waiting_primaries

    @property
    def waiting_poses(self) -> int:
        """Poses waiting for their feature frame."""
        return self._sync.waiting_partners

    @property
    def last_ns(self) -> int | None:
        """Stamp (int ns) of the frame handed out last, None before the first."""
        return self._sync.last_ns

    def add_features(self, features: Features) -> list[Drop]:
        """Queue a feature frame; return drops (a repeated stamp, a full queue)."""
        return self._sync.add_primary(features)

    def add_pose(self, pose: CameraPose) -> list[Drop]:
        """Queue a camera pose; return drops (a repeated stamp, a full queue)."""
        return self._sync.add_partner(pose)

    def pop(
        self, *, hold: bool = False, flush: bool = False
    ) -> tuple[list[tuple[Features, CameraPose]], list[Drop]]:
        """Return the pairs ready in stamp order and the drops (``hold``, ``flush``)."""
        pairs, drops = self._sync.pop(hold=hold, flush=flush)
        return [(f, p) for f, p in pairs if p is not None], drops
