"""The rounds' place in the learning-rate schedule (``FedSettings.round_schedule``)."""

from __future__ import annotations

from itertools import pairwise

import pytest

from dronecap.errors import InputError
from dronecap.federated.state import FedSettings

LR, RATIO = 0.01, 0.03


def _settings(round_lr: float) -> FedSettings:
    cfg = {"lr": LR, "lr_final_ratio": RATIO}
    return FedSettings(
        shards=[], cfg=cfg, pretrain=10_000, local_steps=1000, rounds=5, round_lr=round_lr
    )


def _lr(step: int, lr_steps: int) -> float:
    """The trainer's exponential schedule (``Trainer._lr``)."""
    return LR * RATIO ** min(step / lr_steps, 1.0)


def test_rounds_continue_the_coordinators_schedule_by_default():
    s = _settings(0.0)
    assert [s.round_schedule(r) for r in (1, 2, 5)] == [
        (10_000, 15_000),
        (11_000, 15_000),
        (14_000, 15_000),
    ]


@pytest.mark.parametrize("round_lr", [0.3, 1.0])
def test_rounds_decay_from_round_lr_to_the_final_lr(round_lr):
    s = _settings(round_lr)
    starts = [s.round_schedule(r) for r in range(1, 6)]
    (first, lr_steps), (last, _) = starts[0], starts[-1]
    assert _lr(first, lr_steps) == pytest.approx(round_lr * LR, rel=1e-3)
    assert _lr(last + s.local_steps, lr_steps) == pytest.approx(RATIO * LR)
    # one decay over the rounds: each round starts where the last one ended
    assert {n for _, n in starts} == {lr_steps}
    assert [b - a for (a, _), (b, _) in pairwise(starts)] == [s.local_steps] * 4
    # the first round trains above the whole-budget schedule's lr at that point
    assert _lr(first, lr_steps) > _lr(*_settings(0.0).round_schedule(1))


def test_a_round_lr_at_or_below_the_final_ratio_is_refused():
    with pytest.raises(InputError, match="round_lr"):
        _settings(RATIO).round_schedule(1)
