"""Training run folders: their file names, training into one, evaluating one, reopening one.

A run folder (``dronecap train --out RUN``) holds:

=================== ========================================================================
``checkpoint.pt``   the trainer's full state, resolved configuration included (resumable)
``run.json``        the dataset (path and content hash) and the resolved configuration
                    (:class:`~nerf.resolve.Resolved`: config, scene, reasons)
``metrics.json``    test PSNR/SSIM (and exposure-matched PSNR) per view and mean, train time,
                    ms/step, parameter count, the resolved config, the learned photometric
                    model (written by ``train`` only)
``eval_<stem>.json`` one per dataset ``dronecap eval`` scored the model on
``renders/``        test views as PNGs; ``compare.png``: ground truth | render
``cost.json``       the GAP9 cost of the resolved config (written by the train command)
``progress/``       half-resolution previews of a held-out view at each check of the curve
=================== ========================================================================

:func:`read_resolved` is the one reader of a run's configuration (the cost command uses it).
Torch is imported only by the functions that train or render.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dronecap.datasets.format import Dataset, open_dataset
from dronecap.errors import InputError
from dronecap.files import atomic_output, sha256_file

from . import budget
from .budget import BudgetConfig
from .config import DATA_DECIDED_FIELDS, TrainConfig, config_from_dict
from .resolve import Resolved, choice_lines, resolve
from .sizing import MemoryFn

if TYPE_CHECKING:
    from .trainer import Trainer

CHECKPOINT = "checkpoint.pt"
METRICS = "metrics.json"
RUN_INFO = "run.json"
COST = "cost.json"
RENDERS = "renders"
COMPARE = "compare.png"
COMPARE_VIEWS = 4  # test views in the ground truth | render image
PROGRESS = "progress"
PREVIEW_SCALE = 0.5  # progress previews at half resolution
DATASET_KINDS = ("dataset", "shard")
# fields a resumed run may change: the step target, what the data decides (a model continued
# on another dataset keeps the n_max it was built with) and the MLP products (this CPU's)
RESUMABLE_CHANGES = ("steps", "channels", "resolution", "train_images", "mlp_dtype")


def eval_file(dataset: str | Path) -> str:
    """Name of the result file ``dronecap eval`` writes for ``dataset``: eval_<stem>.json."""
    return f"eval_{Path(dataset).stem}.json"


def write_json(path: str | Path, obj: dict) -> None:
    """Write ``obj`` as indented JSON, atomically (NaN/inf refused: never silently written)."""
    text = json.dumps(obj, indent=2, default=float, allow_nan=False) + "\n"
    with atomic_output(path) as tmp:
        Path(tmp).write_text(text)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise InputError(f"unreadable ({err})", path) from None
    if not isinstance(doc, dict):
        raise InputError("expected a JSON object", path)
    return doc


def read_resolved(run_dir: str | Path) -> Resolved:
    """The resolved configuration a run folder was trained with (from its run.json).

    A run.json written before configs were resolved (``config`` + ``n_max``) is re-resolved
    against the dataset it names, which gives the same values; a folder with a checkpoint but
    no run.json (a federated run) gives its checkpoint's. InputError when that dataset is gone
    or the folder is not a run's.
    """
    path = Path(run_dir) / RUN_INFO
    if not path.exists():
        if (Path(run_dir) / CHECKPOINT).exists():  # e.g. a federated run: its global model
            from .checkpoint import checkpoint_resolved, read_checkpoint

            ckpt = Path(run_dir) / CHECKPOINT
            return checkpoint_resolved(read_checkpoint(ckpt), ckpt)
        raise InputError("not a training run folder (no run.json; run `dronecap train`)", run_dir)
    doc = _read_json(path)
    try:
        if "scene" in doc:
            return Resolved.from_dict(doc)
        cfg = config_from_dict(doc["config"])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"no usable resolved configuration ({err})", path) from None
    dataset = Path(str(doc.get("dataset", "")))
    if not dataset.is_file():
        raise InputError(
            f"written by an older dronecap and its dataset {dataset} is gone: the trained "
            "resolution and image count are unknown (retrain the run)",
            path,
        )
    return resolve(cfg, open_dataset(dataset, kinds=DATASET_KINDS))


def _config_changes(old: TrainConfig, new: TrainConfig) -> list[str]:
    """Fields (other than :data:`RESUMABLE_CHANGES`) whose values differ between two configs."""
    a, b = dataclasses.asdict(old), dataclasses.asdict(new)
    skip = set(RESUMABLE_CHANGES) | ({"n_max"} if old.auto_n_max and new.auto_n_max else set())
    return [
        k for k in a if k not in skip and tuple(np.atleast_1d(a[k])) != tuple(np.atleast_1d(b[k]))
    ]


def _warn(message: str) -> None:
    print(f"dronecap: warning: {message}", file=sys.stderr, flush=True)


def _resume(
    source: Path,
    ds: Dataset,
    ds_path: Path,
    wanted: Resolved,
    other_ok: bool,
    backend: str,
    auto: tuple[str, ...] = (),
) -> Trainer:
    """The trainer of checkpoint ``source`` set to continue to ``wanted`` on ``ds`` (read
    from ``ds_path``). Fields in ``auto`` (data-decided fields the configuration left to
    "auto") keep the resumed model's value: a model trained before they existed goes on
    without them.

    Raises InputError when it was trained with another configuration, or on another dataset
    (content hash; run.json's path for checkpoints older than the hash) unless ``other_ok``.
    """
    from .trainer import Trainer

    trainer = Trainer.load(source, ds, backend=backend)
    old = trainer.resolved
    same = old.dataset_sha256 == wanted.dataset_sha256
    if old.dataset_sha256 is None:  # checkpoint older than the hash: compare the recorded path
        info = source.parent / RUN_INFO
        named = _read_json(info).get("dataset") if info.exists() else None
        same = named is None or Path(str(named)).resolve() == ds_path.resolve()
    if not same:
        if not other_ok:
            raise InputError(
                "was trained on another dataset (its content hash differs); set no_resume to "
                "start over, or resume_from to this run with a new out to continue that "
                "model on this dataset",
                source.parent,
            )
        _warn(f"continuing the model of {source} (trained on another dataset) on this one")
    kept = {k: getattr(old.config, k) for k in auto}
    wanted = Resolved(
        wanted.config.replace(**kept),
        wanted.scene,
        wanted.reasons | {k: "the resumed model's" for k in kept},
        wanted.dataset_sha256,
    )
    changed = _config_changes(old.config, wanted.config)
    if changed:
        raise InputError(
            f"was trained with a different configuration ({', '.join(changed)}); "
            "set no_resume to start over or choose another out",
            source,
        )
    reasons = wanted.reasons | {"n_max": old.reasons.get("n_max", "the resumed model's")}
    config = wanted.config.replace(n_max=old.config.n_max)
    trainer.adopt(Resolved(config, old.scene, reasons, wanted.dataset_sha256))
    return trainer


def train_run(
    dataset_path: str | Path,
    cfg: TrainConfig,
    out_dir: str | Path,
    resume: bool = True,
    progress: bool = True,
    checkpoint_every: int = 500,
    backend: str = "auto",
    evaluate: bool = True,
    resume_from: str | Path | None = None,
    memory_fn: MemoryFn | None = None,
    until: BudgetConfig | None = None,
) -> dict:
    """Train on a dataset file into a run folder, checkpointing, then evaluate all test views.

    ``memory_fn`` sizes a ``sized`` config's table within its memory budget (see
    :func:`nerf.resolve.resolve`); ``until`` is when training stops (:mod:`nerf.budget`:
    the config's step count by default, or a time budget, target PSNR, plateau), and the
    held-out checks it makes are the run's PSNR-vs-time curve (``metrics.json`` "curve",
    half-resolution previews in ``progress/``). When training ends elsewhere than the steps
    asked, the steps trained become the configuration's (:meth:`Trainer.finish`) before
    run.json, the checkpoint and metrics.json are written, so all of them (and the cost report
    read from run.json) give what ran.

    Everything is checked before training starts: the configuration's ranges, the dataset
    (train frames; test or val views unless ``evaluate`` is False), a checkpoint in
    ``out_dir`` (resumed when ``resume``: same configuration, same dataset by content hash).
    ``resume_from`` (a run folder or checkpoint) continues that model instead, on this dataset
    even if it was trained on another one (with a warning).

    Returns:
        the metrics written to ``metrics.json`` (``test`` is None when not evaluated).

    Raises:
        InputError: unreadable dataset, bad configuration, a run folder trained with another
            configuration or dataset, no test views to evaluate, or a diverged training.
    """
    dataset_path, out = Path(dataset_path), Path(out_dir)
    ds = open_dataset(dataset_path, kinds=DATASET_KINDS)
    trainer = _start(ds, dataset_path, cfg, out, resume, resume_from, backend, memory_fn, evaluate)
    info = {"dataset": str(dataset_path.resolve())}
    if resume_from is not None:
        info["resumed_from"] = str(Path(resume_from).resolve())
    write_json(out / RUN_INFO, info | trainer.resolved.to_dict())
    print("\n".join(choice_lines(trainer.resolved, trainer.cfg.sized)))
    until = until or BudgetConfig()
    state, ms, history = _loop(trainer, ds, until, out, progress, checkpoint_every)
    spent = "the time budget was spent" if until.time_budget_s else "the resumed model's"
    trainer.finish(f"the steps trained: {state.stop_reason or spent}")
    write_json(out / RUN_INFO, info | trainer.resolved.to_dict())
    trainer.save(out / CHECKPOINT)
    metrics = evaluate_run(trainer, ds, out, progress) if evaluate else {"test": None}
    import torch

    metrics |= {
        "dataset": str(dataset_path.resolve()),
        "steps": trainer.step,
        "train_seconds": trainer.train_seconds,
        "ms_per_step_median": float(np.median(ms)) if ms else None,
        "threads": torch.get_num_threads(),
        "parameters": trainer.field.parameter_count(),
        "samples": trainer.sample_counts(),
        "photometric": trainer.photometric.summary(),
        "config": dataclasses.asdict(trainer.cfg),
        "reasons": dict(trainer.resolved.reasons),
        "history": history,
        "curve": state.curve,
        "until": dataclasses.asdict(until) | {"stop_reason": state.stop_reason},
    }
    write_json(out / METRICS, metrics)
    return metrics


def _start(
    ds: Dataset,
    dataset_path: Path,
    cfg: TrainConfig,
    out: Path,
    resume: bool,
    resume_from: str | Path | None,
    backend: str,
    memory_fn: MemoryFn | None,
    evaluate: bool,
) -> Trainer:
    """The trainer a run starts from (new, its own checkpoint resumed, or another run's model
    continued), every input checked first (see :func:`train_run`); creates ``out``."""
    from .evaluate import test_views
    from .trainer import Trainer

    wanted = resolve(cfg, ds, sha256_file(dataset_path), memory_fn)
    if evaluate and test_views(ds).size == 0:
        raise InputError(
            "has no test or val views to evaluate on: re-run `dronecap split`, or set no_eval "
            "to train without a test score",
            dataset_path,
        )
    if out.exists() and not out.is_dir():
        raise InputError("is a file, expected a run folder", out)
    out.mkdir(parents=True, exist_ok=True)  # a read-only or full target fails before training
    ckpt = out / CHECKPOINT
    auto = tuple(k for k in DATA_DECIDED_FIELDS if getattr(cfg, k) == "auto")
    if resume_from is not None:
        source = Path(resume_from)
        source = source / CHECKPOINT if source.is_dir() else source
        return _resume(source, ds, dataset_path, wanted, True, backend, auto)
    if resume and ckpt.exists():
        return _resume(ckpt, ds, dataset_path, wanted, False, backend, auto)
    return Trainer(wanted, ds, backend=backend)


def _loop(
    trainer: Trainer,
    ds: Dataset,
    until: BudgetConfig,
    out: Path,
    progress: bool,
    checkpoint_every: int,
) -> tuple[budget.BudgetState, list[float], list[dict]]:
    """Train until ``until`` says stop, checking held-out views and checkpointing on the way
    (a checkpoint on Ctrl-C too). Returns (the budget state, ms of every step, the history
    rows: one every 100 steps and the last)."""
    from dronecap.progress import progress_bar

    ckpt = out / CHECKPOINT
    state = budget.start(until, trainer.cfg.steps, trainer.step, trainer.train_seconds)
    held_out = budget.held_out_views(ds.split, until.check_views)
    ms: list[float] = []
    history: list[dict] = []
    bar = progress_bar(
        total=state.planned_steps, initial=trainer.step, desc="train", unit="step",
        disable=not progress,
    )  # fmt: skip
    try:
        while not budget.finished(state, trainer.step):
            trainer.plan(state.planned_steps)  # the lr decay follows the plan
            log = trainer.train_step()
            ms.append(log["ms"])
            budget.after_step(until, state, trainer.step, trainer.train_seconds, log["ms"] / 1e3)
            bar.total = state.planned_steps
            bar.update(1)
            if budget.check_due(until, state, trainer.step) and held_out.size:
                _check(trainer, ds, held_out, until, state, out)
            done = budget.finished(state, trainer.step)
            if trainer.step % 10 == 0 or done:
                bar.set_postfix(
                    loss=f"{log['loss']:.4f}",
                    psnr=f"{log['psnr']:.1f}",
                    spr=f"{log['samples'] / max(log['rays'], 1):.1f}",
                    ms=f"{np.median(ms[-50:]):.0f}",
                )
            if trainer.step % 100 == 0 or done:
                history.append(
                    {k: log[k] for k in ("step", "loss", "psnr", "samples", "rays")}
                    | {"seconds": trainer.train_seconds}
                )
            if trainer.step % checkpoint_every == 0 and not done:
                trainer.save(ckpt)
    except KeyboardInterrupt:
        bar.close()
        trainer.save(ckpt)
        raise
    bar.close()
    return state, ms, history


def _check(
    trainer: Trainer,
    ds: Dataset,
    views: np.ndarray,
    until: BudgetConfig,
    state: budget.BudgetState,
    out: Path,
) -> None:
    """A held-out check: PSNR of ``views`` onto the curve (may stop the run) and a
    half-resolution preview of the first one in ``progress/step_NNNNNN.png``."""
    from .outputs import write_png
    from .render import render_preview

    psnr = trainer.evaluate(ds, views)["psnr"]
    why = budget.record_check(until, state, trainer.step, trainer.train_seconds, psnr)
    preview = render_preview(
        trainer.volume(), ds.poses[views[0]], ds.camera_of(views[0]), trainer.scene.background,
        PREVIEW_SCALE,
    )  # fmt: skip
    write_png(out / PROGRESS / f"step_{trainer.step:06d}.png", preview)
    if why:
        print(f"dronecap: stopping at step {trainer.step}: {why}", file=sys.stderr, flush=True)


def evaluate_run(trainer: Trainer, ds: Dataset, out: Path, progress: bool = True) -> dict:
    """Evaluate all test views, write their renders and ``compare.png``; {"test": scores}."""
    from .evaluate import ground_truth
    from .outputs import side_by_side, write_png

    res = trainer.evaluate_all(ds, progress)
    images = res.pop("images")
    for v, img in zip(res["per_view"], images, strict=True):
        write_png(out / RENDERS / f"test_{v['index']:03d}.png", img)
    pairs = [
        (ground_truth(ds, v["index"], trainer.scene.background), img)
        for v, img in list(zip(res["per_view"], images, strict=True))[:COMPARE_VIEWS]
    ]
    if pairs:
        write_png(out / COMPARE, side_by_side(pairs))
    return {"test": res}


def open_run(run_dir: str | Path, dataset: str | Path | None = None) -> tuple[Trainer, Dataset]:
    """(trainer, dataset) of a run folder; ``dataset`` defaults to the one in ``run.json``.

    Raises InputError when the folder holds no checkpoint, its weights are not finite, or the
    dataset's channels differ from the model's.
    """
    from .trainer import Trainer

    run_dir = Path(run_dir)
    if not (run_dir / CHECKPOINT).exists():
        raise InputError("not a training run (no checkpoint.pt; run `dronecap train`)", run_dir)
    if dataset is None:
        info_path = run_dir / RUN_INFO
        if not info_path.exists():
            raise InputError("no run.json naming the dataset; give the dataset setting", run_dir)
        dataset = _read_json(info_path).get("dataset")
        if not isinstance(dataset, str):
            raise InputError("names no dataset; give the dataset setting", info_path)
    ds = open_dataset(dataset, kinds=DATASET_KINDS)
    trainer = Trainer.load(run_dir / CHECKPOINT)
    if not trainer.weights_finite():
        raise InputError("the checkpoint holds non-finite weights", run_dir / CHECKPOINT)
    if ds.channels != trainer.scene.channels:
        raise InputError(
            f"has {ds.channels} channels but the run's model has {trainer.scene.channels}", dataset
        )
    return trainer, ds


def eval_run(
    run_dir: str | Path, dataset: str | Path | None = None, progress: bool = True
) -> tuple[Path, dict]:
    """Score a run's model on the test views of ``dataset`` (default: its own) into
    ``RUN/eval_<dataset stem>.json`` (never metrics.json); returns (that path, the record).

    Raises InputError (see :func:`open_run`) or when the dataset has no test or val views.
    """
    from .evaluate import test_views

    run_dir = Path(run_dir)
    trainer, ds = open_run(run_dir, dataset)
    ds_path = Path(dataset) if dataset else Path(_read_json(run_dir / RUN_INFO)["dataset"])
    if test_views(ds).size == 0:
        raise InputError("has no test or val views to evaluate on", ds_path)
    res = trainer.evaluate(ds, progress=progress)
    record = {
        "dataset": str(ds_path.resolve()),
        "dataset_sha256": sha256_file(ds_path),
        "trained_on_sha256": trainer.resolved.dataset_sha256,
        "steps": trainer.step,
        "test": res,
    }
    out = run_dir / eval_file(ds_path)
    write_json(out, record)
    return out, record
