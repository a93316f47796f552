"""`dronecap eval`: score a trained run on the test views of a dataset (PSNR/SSIM, scikit-image)
into RUN_DIR/eval_<dataset stem>.json (the training record, metrics.json, is never touched).

dronecap eval [RUN_DIR] [--dataset dataset.h5]
"""

from __future__ import annotations

from dataclasses import dataclass

from dronecap.settings import ProgressSettings, TorchSettings, input_setting, setting


@dataclass(kw_only=True)
class Settings(TorchSettings, ProgressSettings):
    """Options of ``dronecap eval``."""

    run_dir: str | None = input_setting("run dir", "WORKDIR/runs/train")
    dataset: str | None = setting(None, help="dataset.h5 (default: the one the run was trained on)")


def run(s: Settings) -> int:
    """Evaluate and write the dataset's eval file."""
    from dronecap import workspace
    from dronecap.cpu import check_threads, use_torch_threads
    from dronecap.nerf.evaluate import scores_line
    from dronecap.nerf.run_dir import eval_run

    run_dir = workspace.resolve(s.workdir, s.run_dir, workspace.TRAIN_RUN)
    check_threads(s.threads)
    use_torch_threads(s.threads)
    out, rec = eval_run(run_dir, s.dataset, not s.no_progress)
    print(f"{out}: {scores_line(rec['test'])}")
    return 0
