"""Checks every drone's update passes before it is averaged.

A reply is left out of the round, with one logged reason, when (in this order):

- its arrays are not the global model's: other names, shapes, or a non-floating dtype
  (only float16/float32 travel);
- any value is non-finite, or larger in magnitude than :data:`MAX_ABS` (a trained hash table
  and MLP hold values of order 1-100, grid densities up to some 1000s);
- it claims another train-image count than its shard holds: FedAvg weights by that count, and
  the server knows each shard's size (it read ``federation.json``'s shards), so a drone cannot
  take the average over by claiming 10^9 examples;
- its change from the global model (L2 norm over every array) is more than :data:`NORM_FACTOR`
  times the median change of the other drones (robust: one outlier does not move the median).

The round then completes with the others; when none is left the round fails as when every
drone failed.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

MAX_ABS = 1.0e5  # largest |value| accepted in an update (fp16 itself stops at 65504)
NORM_FACTOR = 10.0  # an update's change may be at most this many times the others' median
FLOAT_DTYPES = (np.dtype(np.float16), np.dtype(np.float32))


def array_problem(
    update: Mapping[str, np.ndarray], reference: Mapping[str, np.ndarray]
) -> str | None:
    """Why ``update`` ({name: array}) cannot be averaged into ``reference`` (the global model's
    arrays, same names and shapes expected), or None when its arrays are acceptable."""
    if set(update) != set(reference):
        missing, extra = sorted(set(reference) - set(update)), sorted(set(update) - set(reference))
        return f"arrays do not match the model (missing {missing}, unexpected {extra})"
    for name, a in update.items():
        a = np.asarray(a)
        if a.shape != np.shape(reference[name]):
            return f"{name} has shape {a.shape}, expected {np.shape(reference[name])}"
        if a.dtype not in FLOAT_DTYPES:
            return f"{name} has dtype {a.dtype}, expected float16 or float32"
        finite = np.isfinite(a)
        if not finite.all():
            return f"{name} holds {int(a.size - finite.sum())} non-finite values (NaN/inf)"
        peak = float(np.abs(a).max(initial=0.0))
        if peak > MAX_ABS:
            return f"{name} holds a value of magnitude {peak:.3g} (limit {MAX_ABS:g})"
    return None


def count_problem(claimed: float, known: float) -> str | None:
    """Why a drone's claimed train-image count ``claimed`` is refused (``known``: its shard's
    train images, as the server read them), or None when they agree."""
    if not np.isfinite(claimed) or claimed != known:
        return f"claims {claimed:g} train images, its shard holds {known:g}"
    return None


def change_norm(update: Mapping[str, np.ndarray], reference: Mapping[str, np.ndarray]) -> float:
    """L2 norm of ``update - reference`` over every array (float64)."""
    total = 0.0
    for name, a in update.items():
        d = np.asarray(a, np.float64) - np.asarray(reference[name], np.float64)
        total += float(np.dot(d.reshape(-1), d.reshape(-1)))
    return float(np.sqrt(total))


def norm_outliers(norms: Mapping[int, float], factor: float = NORM_FACTOR) -> dict[int, str]:
    """Drones whose change norm exceeds ``factor`` x the median of the others' norms.

    ``norms``: drone -> change norm. With one drone there is nothing to compare: none.
    Returns drone -> reason."""
    out: dict[int, str] = {}
    for k, n in norms.items():
        others = [v for j, v in norms.items() if j != k]
        if not others:
            continue
        ref = float(np.median(others))
        if n > factor * ref:
            out[k] = (
                f"its change has norm {n:.3g}, more than {factor:g} x the others' median {ref:.3g}"
            )
    return out


def screen(
    updates: Mapping[int, Mapping[str, np.ndarray]],
    reference: Mapping[str, np.ndarray],
    claimed: Mapping[int, float],
    known: Mapping[int, float],
) -> dict[int, str]:
    """The drones to leave out of a round and why.

    ``updates``: drone -> {name: array} (the drone's model as received, full arrays);
    ``reference``: the global model the round started from; ``claimed``: drone -> its
    self-reported train-image count; ``known``: drone -> its shard's train-image count.
    Returns drone -> reason (empty: all accepted).
    """
    rejected: dict[int, str] = {}
    for k, u in updates.items():
        why = array_problem(u, reference) or count_problem(float(claimed[k]), float(known[k]))
        if why:
            rejected[k] = why
    norms = {k: change_norm(u, reference) for k, u in updates.items() if k not in rejected}
    rejected.update(norm_outliers(norms))
    return rejected
