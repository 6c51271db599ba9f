"""A source's bookkeeping of sequence numbers (``tether.inputs.Source.offer``): duplicates against
reordered samples, on arbitrary streams, against a plain model of the rule."""

from __future__ import annotations

import random
from typing import NamedTuple

import pytest

from tether.inputs import RECENT_SEQS, Source


class Msg(NamedTuple):
    seq: int
    k: int


def model(seqs: list[int]) -> tuple[int, int, int]:
    """The rule, written plainly: a sample not newer than the newest is stale; a stale one is a
    duplicate if its number was received before or lies more than RECENT_SEQS behind the newest,
    else it is reordered. Returns (stale, duplicates, reordered)."""
    seen: set[int] = set()
    newest = None
    stale = dup = reo = 0
    for q in seqs:
        if newest is not None and q <= newest:
            stale += 1
            if q in seen or q < newest - RECENT_SEQS:
                dup += 1
            else:
                reo += 1
        else:
            newest = q
        seen.add(q)
    return stale, dup, reo


def offered(seqs: list[int]) -> tuple[int, int, int]:
    src = Source("k", Msg, None, keep=False)
    for q in seqs:
        src.offer(Msg(q, q))
    assert src.received == len(seqs)
    assert src.newest.seq == max(seqs)
    return src.stale, src.duplicates, src.reordered


@pytest.mark.parametrize("seed", range(40))
def test_duplicates_and_reorderings_are_told_apart_as_the_rule_says(seed: int) -> None:
    rng = random.Random(seed)
    seqs, q = [], 0
    for _ in range(3000):
        r = rng.random()
        if r < 0.6:
            q += 1 if rng.random() < 0.9 else rng.randint(2, 3 * RECENT_SEQS)  # on, or a burst lost
            seqs.append(q)
        elif r < 0.8:
            seqs.append(q - rng.randint(0, 2 * RECENT_SEQS))  # late copies, replays, far behind
        elif seqs:
            seqs.append(rng.choice(seqs[-600:]))  # an exact repeat of something recent
    assert offered(seqs) == model(seqs)


def test_the_window_edges() -> None:
    seqs = [1000, 1000 - RECENT_SEQS, 1000 - RECENT_SEQS - 1, 1000 - RECENT_SEQS, 1000]
    assert offered(seqs) == model(seqs) == (4, 3, 1)


def test_a_forged_huge_sequence_number_costs_nothing_and_is_counted_like_any_other() -> None:
    """A forged sample far ahead becomes the newest (the gate, not this bookkeeping, judges it); the
    window is then started afresh, never shifted by 2**62 bits."""
    seqs = [1, 2, 2**62, 3, 2**62, 2**62 - 1]
    src = Source("k", Msg, None, keep=False)
    for q in seqs:
        src.offer(Msg(q, 0))
    assert src.recent.bit_length() <= RECENT_SEQS + 1
    assert (src.stale, src.duplicates, src.reordered) == model(seqs) == (3, 2, 1)


@pytest.mark.parametrize("seed", range(20))
def test_had_is_true_exactly_for_numbers_received_within_the_window(seed: int) -> None:
    """``Source.had`` (a lockstep receiver drops a copy it had): true only for a number received
    and within RECENT_SEQS of the newest; a number too far behind to tell is not known to be had,
    so that a sample still needed is never dropped as a copy."""
    rng = random.Random(seed)
    src = Source("k", Msg, None, keep=False)
    seen: set[int] = set()
    for _ in range(400):
        q = rng.randrange(0, 600)
        src.offer(Msg(q, q))
        seen.add(q)
    newest = max(seen)
    for q in range(0, newest + 5):
        assert src.had(Msg(q, q)) == (q in seen and newest - q <= RECENT_SEQS), q
