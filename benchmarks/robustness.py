"""Robustness of the default pipeline to each camera/link degradation of a real nano-drone.

A simulated corridor flight (same route, seed and scene for every case) is rendered clean, with
each degradation of ``dronecap simulate`` alone at its default level, and with all of them
(``--sensor aideck``: 324x244 HM01B0 over Wi-Fi), then run through the default commands
``simulate -> ingest -> sfm -> split -> train`` (one thread each). Per case: frames delivered and
kept, % registered, ATE (% of the trajectory extent), rotation error, focal-length error against
the true lens, test PSNR/SSIM on the flight's own test views, and PSNR/SSIM against noise-free
renders of the same test poses (a reference flight rendered without noise or exposure drift).
For the distortion case the same dataset is also trained with the distortion stripped from its
camera ("distortion ignored": pinhole rays).

    nice .venv/bin/python benchmarks/robustness.py [--frames 240] [--steps 1500]
        [--cases clean,distortion,...] [--work /tmp/dronecap-robustness]
        [--train-set FIELD=VALUE ...]

``--train-set`` passes a training setting (``dronecap train --set``) to every case, e.g.
``learn_exposure=on``; give it its own ``--work`` (finished cases are cached there). Every test
PSNR also has its exposure-matched twin (per view, the least-squares gain of the render to the
ground truth applied first: ``psnr_exposure_matched`` of the evaluation).

``--snapshot`` runs everything on the last commit (``git archive HEAD`` unpacked under the work
folder), not on the shared work tree where other engineers' edits are in progress. Each case's
work folder is kept; a case whose results file exists is not re-run (delete its
folder to redo it). Writes benchmarks/results/robustness.md and robustness.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import time
from pathlib import Path

import numpy as np
from snapshot import RESULTS, rerun_on_snapshot
from snapshot import dronecap_command as sh

# case -> (simulate flags, kind): "geometric"/"timing" judged on their own test views,
# "photometric" also against noise-free renders of the test poses
CASES: dict[str, tuple[list[str], str]] = {
    "clean": ([], "reference"),
    "distortion": (["--distortion"], "geometric"),
    "principal-point": (["--principal-offset"], "geometric"),
    "blur": (["--blur"], "geometric"),
    "dropped": (["--drop"], "timing"),
    "duplicated": (["--duplicate"], "timing"),
    "torn": (["--torn"], "timing"),
    "noise": (["--noise"], "photometric"),
    "jpeg": (["--jpeg"], "photometric"),
    "vignetting": (["--vignetting"], "photometric"),
    "exposure": (["--exposure-drift"], "photometric"),
    "aideck (all)": (["--sensor", "aideck"], "all"),
}
NOISE_FREE = ["--noise", "0,0", "--exposure-drift", "0"]


def scores(test: dict, clean: bool = False) -> tuple[float, float, float]:
    """(PSNR, SSIM, exposure-matched PSNR) of an evaluation's "test" record; with ``clean``
    (ground truth rendered without the camera's effects) PSNR and SSIM of the render alone."""
    if clean and "psnr_radiance" in test:
        return test["psnr_radiance"], test["ssim_radiance"], test["psnr_exposure_matched"]
    return test["psnr"], test["ssim"], test["psnr_exposure_matched"]


def reference_frames(work: Path, frames: int) -> np.ndarray:
    """Noise-free renders of every source frame: uint8 [N, 160, 160] (rendered once)."""
    from dronecap.simulator.simulate import render_flight

    path = work / f"reference-{frames}.npy"
    if not path.exists():
        import dataclasses as dc

        from dronecap.simulator.simulate import capture_preset

        clean = capture_preset("clean")
        sensor = dc.replace(clean.sensor, read_noise=0.0, shot_noise=0.0, exposure_drift=0.0)
        it, _ = render_flight("corridor", frames, 0, dc.replace(clean, sensor=sensor))
        tmp = path.with_name(f".reference-{os.getpid()}.npy")
        np.save(tmp, np.stack(list(it)))
        os.replace(tmp, path)
    return np.load(path)


def with_images(src: Path, dst: Path, reference: np.ndarray, gt: dict) -> None:
    """``src`` dataset with each frame's image replaced by the noise-free render of the source
    frame it shows (geometry unchanged)."""
    from dronecap.datasets import open_dataset, write_dataset

    ds = open_dataset(src)
    recs = [gt["frames"][int(i)] for i in ds.source_index]
    shows = [r.get("shows", r["source_frame"]) for r in recs]
    images = reference[np.asarray(shows)][..., None]
    write_dataset(dst, dataclasses.replace(ds, images=images))


def pinhole_copy(src: Path, dst: Path) -> None:
    """``src`` dataset with the distortion stripped from its camera."""
    from dronecap.datasets import open_dataset, write_dataset

    ds = open_dataset(src)
    write_dataset(dst, dataclasses.replace(ds, intrinsics=ds.intrinsics.pinhole()))


def true_focal(gt: dict) -> float:
    """fx of the true lens in the 160x160 frames ingest makes (centre crop, then resize)."""
    k = gt["intrinsics"]
    return float(k["fx"]) * 160 / min(int(k["width"]), int(k["height"]))


def case_dir(work: Path, name: str) -> Path:
    """Work folder of a case ("aideck (all)" -> aideck_all)."""
    return work / re.sub(r"\W+", "_", name).strip("_")


def run_case(
    name: str, work: Path, frames: int, steps: int, train: bool = True, sets: tuple[str, ...] = ()
) -> dict:
    """Simulate, ingest, sfm, split, train (and evaluate) one case; returns its record
    (``train`` False: stop after SfM; ``sets``: ``--set`` assignments for training)."""
    flags, kind = CASES[name]
    d = case_dir(work, name)
    done = d / "result.json"
    if done.exists():
        rec = json.loads(done.read_text())
        if "psnr" in rec or "error" in rec or not train:
            return rec
    d.mkdir(parents=True, exist_ok=True)
    log = d / "log.txt"
    stamp = d / "commit.txt"  # the code that ran the case's first stage (stages resume)
    if not stamp.exists():
        stamp.write_text(os.environ.get("DRONECAP_SNAPSHOT", "work tree"))
    rec: dict = {"case": name, "kind": kind, "flags": " ".join(flags),
                 "commit": stamp.read_text().strip()}  # fmt: skip
    t0 = time.perf_counter()
    try:
        sim = ["simulate", "--frames", str(frames), "--seed", "0", *flags]
        if not (d / "flight.json").exists():  # finished stages are not re-run
            sh([*sim, "-o", str(d / "flight.mp4")], log)
        gt = json.loads((d / "flight.json").read_text())
        rec["delivered"] = gt["stream"]["delivered"]
        if not (d / "frames.h5").exists():
            sh(["ingest", str(d / "flight.mp4"), "--workdir", str(d)], log)
        from dronecap.datasets import open_dataset

        rec["kept"] = open_dataset(d / "frames.h5").n
        if not (d / "posed.h5").exists():
            sh(["sfm", "--gt", str(d / "flight.json"), "--threads", "1", "--workdir", str(d)], log)
        rep = json.loads((d / "sfm" / "report.json").read_text())
        acc = rep.get("accuracy", {})
        rec.update(
            registered=rep["registered"],
            registered_pct=100 * rep["registration_rate"],
            ate_pct=acc.get("ate_percent"),
            rot_median_deg=acc.get("rot_median_deg"),
        )
        posed = open_dataset(d / "posed.h5")
        rec["focal_err_pct"] = 100 * (posed.intrinsics.fx / true_focal(gt) - 1)
        dist = [round(float(x), 3) for x in posed.intrinsics.distortion]
        rec["camera"] = f"{posed.intrinsics.model} {dist}"
        if not train:
            raise StopIteration
        sh(["split", "--workdir", str(d)], log)
        train_cmd = ["train", "--threads", "1", "--steps", str(steps), "--no-progress"]
        train_cmd += [arg for item in sets for arg in ("--set", item)]
        sh([*train_cmd, "--workdir", str(d)], log)
        m = json.loads((d / "runs" / "train" / "metrics.json").read_text())["test"]
        rec["psnr"], rec["ssim"], rec["psnr_matched"] = scores(m)
        rec["test_views"] = m["views"]
        if kind in ("photometric", "reference", "all"):
            ref = reference_frames(work, frames)
            if kind != "all":  # the 324x244 lens needs its own noise-free renders: not done
                with_images(d / "dataset.h5", d / "dataset_ref.h5", ref, gt)
                sh(["eval", str(d / "runs" / "train"), "--dataset", str(d / "dataset_ref.h5"),
                    "--threads", "1", "--no-progress"], log)  # fmt: skip
                ref_eval = d / "runs" / "train" / "eval_dataset_ref.json"
                test = json.loads(ref_eval.read_text())["test"]
                rec["psnr_ref"], rec["ssim_ref"], rec["psnr_ref_matched"] = scores(test, clean=True)
        if name == "distortion":
            pinhole_copy(d / "dataset.h5", d / "dataset_pinhole.h5")
            sh([*train_cmd, str(d / "dataset_pinhole.h5"), "--out", str(d / "runs" / "pinhole")],
               log)  # fmt: skip
            m = json.loads((d / "runs" / "pinhole" / "metrics.json").read_text())["test"]
            rec["psnr_ignored"], rec["ssim_ignored"] = m["psnr"], m["ssim"]
    except StopIteration:
        rec["note"] = "not trained (time)"
    except Exception as err:  # noqa: BLE001 - a failed case is a result, recorded as such
        rec["error"] = str(err).splitlines()[0][:200] if str(err) else type(err).__name__
    rec["seconds"] = time.perf_counter() - t0
    done.write_text(json.dumps(rec, indent=1))
    return rec


def link_and_ingest(d: Path) -> dict[str, str]:
    """What the link did (flight.json) and what ingest dropped (its summary line in the log)."""
    out = {}
    if (d / "flight.json").exists():
        st = json.loads((d / "flight.json").read_text())["stream"]
        out["link"] = (f"{len(st['dropped'])} lost, {len(st['duplicated'])} dup., "
                       f"{len(st['torn'])} torn")  # fmt: skip
    if (d / "log.txt").exists():
        m = re.search(
            r"decoded \d+ frames, kept \d+, dropped: ([^(\n]*)", (d / "log.txt").read_text()
        )
        if m:
            out["ingest"] = m.group(1).strip().rstrip(";").split(";")[0]
    return out


def fmt(x: object, spec: str) -> str:
    """Table cell: formatted number or a dash."""
    return "–" if x is None else format(x, spec)


def table(recs: list[dict], args: argparse.Namespace, load: str) -> str:
    """The results page (markdown)."""
    clean = next((r for r in recs if r["case"] == "clean" and "psnr" in r), None)
    sets = "".join(f" --train-set {item}" for item in args.train_set)
    train_sets = "".join(f" --set {item}" for item in args.train_set)
    lines = [
        "# Robustness of the default pipeline to nano-drone camera and link defects",
        "",
        f"Command: `nice .venv/bin/python benchmarks/robustness.py --frames {args.frames} "
        f"--steps {args.steps}{sets}` (corridor, seed 0, default `ingest`, `sfm --gt --threads 1`, "
        f"`split`, `train --threads 1 --steps {args.steps}{train_sets}`). Code: commit "
        f"{', '.join(sorted({r.get('commit', '?') for r in recs}))} (per case in the last "
        f"column). Load: {load}.",
        "",
        "Δ PSNR = test PSNR minus the clean flight's (own test views). PSNR vs ref: the same run "
        "evaluated against noise-free, drift-free renders of the test poses (photometric cases). "
        "matched: exposure-matched PSNR (each render scaled by its least-squares gain to the "
        "ground truth first).",
        "",
        "| case | flags | link (truth) | ingest dropped | delivered / kept | registered | ATE "
        "| rot. median | SfM camera | focal err. | test PSNR / SSIM | matched | Δ PSNR "
        "| PSNR / SSIM vs ref | matched vs ref | note | commit |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in recs:
        delta = r["psnr"] - clean["psnr"] if clean and "psnr" in r else None
        note = r.get("error", r.get("note", ""))
        if "psnr_ignored" in r:
            note = (f"distortion ignored: {r['psnr_ignored']:.2f} dB / {r['ssim_ignored']:.3f}"
                    f" ({r['psnr_ignored'] - r['psnr']:+.2f} dB)")  # fmt: skip
        ref = f"{r['psnr_ref']:.2f} / {r['ssim_ref']:.3f}" if "psnr_ref" in r else "–"
        camera = re.sub(r"np.float64[(]([^)]*)[)]", r"\1", r.get("camera", "–"))
        lines.append(
            f"| {r['case']} | `{r['flags']}` | {r.get('link', '–')} | {r.get('ingest', '–')} "
            f"| {r.get('delivered', '–')} / {r.get('kept', '–')} "
            f"| {fmt(r.get('registered_pct'), '.1f')} % | {fmt(r.get('ate_pct'), '.2f')} % "
            f"| {fmt(r.get('rot_median_deg'), '.2f')}° "
            f"| {camera} "
            f"| {fmt(r.get('focal_err_pct'), '+.2f')} % "
            f"| {fmt(r.get('psnr'), '.2f')} / {fmt(r.get('ssim'), '.3f')} "
            f"| {fmt(r.get('psnr_matched'), '.2f')} "
            f"| {fmt(delta, '+.2f')} | {ref} | {fmt(r.get('psnr_ref_matched'), '.2f')} "
            f"| {note} | {r.get('commit', '?')} |"
        )
    return "\n".join(lines) + "\n"


def plot(recs: list[dict], path: Path) -> None:
    """Bar charts per case: registered %, ATE %, and test PSNR where trained."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["case"] for r in recs]
    trained = any("psnr" in r for r in recs)
    fig, axes = plt.subplots(1, 3 if trained else 2, figsize=(13 if trained else 9, 4))
    panels = [("registered_pct", "registered %", 95.0), ("ate_pct", "ATE % of extent", 0.5)]
    if trained:
        panels.append(("psnr", "test PSNR (dB)", None))
    for ax, (key, label, floor) in zip(axes, panels, strict=True):
        ax.bar(names, [r.get(key) or 0.0 for r in recs], color="tab:blue")
        if floor is not None:
            ax.axhline(floor, color="k", ls="--", lw=1)
        ax.set_ylabel(label)
        ax.tick_params(axis="x", rotation=60, labelsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    ap.add_argument("--work", type=Path, default=Path("/tmp/dronecap-robustness"))
    ap.add_argument("--results", default="robustness", help="results file stem")
    ap.add_argument("--snapshot", action="store_true", help="run on the committed HEAD")
    ap.add_argument("--sfm-only", default="", help="comma-separated cases run only up to SfM")
    ap.add_argument("--table-only", action="store_true", help="tabulate finished cases only")
    ap.add_argument(
        "--train-set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="training setting for every case (dronecap train --set; repeatable)",
    )
    args = ap.parse_args()
    if args.snapshot:
        args.work.mkdir(parents=True, exist_ok=True)
        rerun_on_snapshot(args.work, Path(__file__))
    names = [c.strip() for c in args.cases.split(",")]
    if unknown := [c for c in names if c not in CASES]:
        raise SystemExit(f"unknown cases {unknown}; known: {list(CASES)}")
    args.work.mkdir(parents=True, exist_ok=True)
    recs = []
    for name in names:
        print(f"== {name}", flush=True)
        if args.table_only:
            done = case_dir(args.work, name) / "result.json"
            if done.exists():
                recs.append({**json.loads(done.read_text()), **link_and_ingest(done.parent)})
            continue
        train = name not in args.sfm_only.split(",")
        rec = run_case(name, args.work, args.frames, args.steps, train, tuple(args.train_set))
        recs.append({**rec, **link_and_ingest(case_dir(args.work, name))})
        print(json.dumps(recs[-1]), flush=True)
    load = open("/proc/loadavg").read().split()[:3]
    text = table(recs, args, f"load average {' '.join(load)} at the end (2 cores)")
    print(text)

    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{args.results}.md").write_text(text)
    plot(recs, RESULTS / f"{args.results}.png")
    print(f"wrote {RESULTS / args.results}.md/.png")


if __name__ == "__main__":
    main()
