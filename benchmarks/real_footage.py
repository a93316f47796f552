"""Real nano-drone footage and drone capture folders through the default commands.

Cases (each ``dronecap ingest SOURCE && dronecap sfm`` in its own work folder, default options
unless the case says otherwise):

- ``himax test_23 / test_10 / test_2``: the real Himax HM01B0 sequences (324x244 PGM folders);
- ``himax test_15 (camera of test_23)``: ``sfm --camera-from`` test_23's posed.h5 (same sensor);
- ``lego orbit video``: the 200 lego test views composited on pure 255 white, gray, as an mp4
  (``sfm --gt`` against the Blender poses);
- ``sim nanocockpit|pulp-dronet, priors / no priors``: ``dronecap simulate --format F`` (corridor,
  noisy drifting onboard state), ``ingest`` of the capture folder, ``sfm --gt flight.json``;
  "no priors" removes ``extra/prior_*`` from frames.h5 first. With priors the result is in metres
  and z-up, so the Umeyama alignment to the ground truth should need scale 1 and no tilt: the
  metric scale error is |scale - 1| and the gravity error the tilt of that alignment.

Columns: frames in (decoded) / kept, registered %, mean reprojection error (px), sfm seconds
(wall clock, single thread), ATE (% of the extent), rotation median (deg), metric scale error
(%), gravity error (deg), and the remedy the retries used. Writes
``benchmarks/results/real_footage.md`` and ``real_footage.png``. Usage::

    OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/real_footage.py [--only NAME ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from snapshot import DATA, RESULTS

HIMAX = DATA / "himax_hm01b0"
LEGO = DATA / "nerf_synthetic_160" / "lego"
DRONECAP = [sys.executable, "-m", "dronecap.cli"]

FLOORS = {  # case -> (registered %, ATE %, rotation deg, scale error %, gravity deg)
    "himax test_23": (95.0, None, None, None, None),
    "himax test_10": (95.0, None, None, None, None),
    "himax test_2": (80.0, None, None, None, None),
    "himax test_15 (camera of test_23)": (50.0, None, None, None, None),
    "lego orbit video": (95.0, 0.5, 1.0, None, None),
    "sim nanocockpit, priors": (98.0, None, None, 2.0, 2.0),
    "sim pulp-dronet, priors": (98.0, None, None, 2.0, 2.0),
}


def dronecap(args: list[str], log: Path) -> int:
    """Run ``dronecap ARGS`` single-threaded in the log's folder (never in the repository, whose
    ``dronecap/`` folder would shadow a snapshot), output appended to ``log``; the exit code."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "DRONECAP_PROGRESS": "off"}
    with open(log, "a") as f:
        f.write(f"$ dronecap {' '.join(args)}\n")
        f.flush()
        return subprocess.call([*DRONECAP, *args], stdout=f, stderr=f, env=env, cwd=log.parent)


def lego_video(path: Path) -> Path:
    """The 200 lego test views on 255 white, gray, as an mp4 (30 fps), and its ground truth."""
    import cv2
    import numpy as np

    from dronecap.sfm.blender_flight import blender_flight

    gt = path.with_name(path.stem + "_gt.json")  # not STEM.json: ingest would read intrinsics
    if path.exists() and gt.exists():
        return gt
    meta = json.loads((LEGO / "transforms_test.json").read_text())
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (160, 160))
    for fr in meta["frames"]:
        rgba = cv2.imread(str(LEGO / (fr["file_path"] + ".png")), cv2.IMREAD_UNCHANGED)
        a = rgba[..., 3:4].astype(np.float32) / 255.0
        rgb = rgba[..., :3].astype(np.float32) * a + 255.0 * (1.0 - a)
        gray = cv2.cvtColor(np.round(rgb).astype(np.uint8), cv2.COLOR_BGR2GRAY)
        writer.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    writer.release()
    _, doc = blender_flight(LEGO)  # source frame i of the video = test view i
    gt.write_text(json.dumps(doc))
    return gt


def strip_priors(frames: Path) -> None:
    """Remove the telemetry priors from a frames.h5 (the "no priors" runs)."""
    from dronecap.datasets.format import open_dataset, write_dataset

    ds = open_dataset(frames)
    for name in ("prior_c2w", "prior_valid"):
        ds.extra.pop(name, None)
    write_dataset(frames, ds)


def slug(name: str) -> str:
    """Folder name of a case."""
    return name.replace(" ", "_").replace("(", "").replace(")", "").replace(",", "")


def run_case(name: str, work: Path, n_sim: int, sfm_extra: Sequence[str] = ()) -> dict:
    """Ingest + sfm (with ``sfm_extra`` options) of one case in ``work/<slug>``; a table row."""
    d = work / slug(name)
    d.mkdir(parents=True, exist_ok=True)
    log = d / "log.txt"
    log.write_text("")
    sfm_args: list[str] = ["sfm", "--workdir", str(d), "--quiet", "--threads", "1", *sfm_extra]
    if name.startswith("himax"):
        seq = name.split()[1]
        source = HIMAX / seq
        if "camera of" in name:
            sfm_args += ["--camera-from", str(work / "himax_test_23" / "posed.h5")]
    elif name.startswith("lego"):
        source = d / "lego_orbit.mp4"
        sfm_args += ["--gt", str(lego_video(source))]
    else:
        fmt = name.split()[1].rstrip(",")
        source = work / f"capture_{fmt}_{n_sim}"  # shared by the runs with and without priors
        if not (source / "flight.json").exists():
            sim = ["simulate", "-o", str(source), "--format", fmt, "--frames", str(n_sim)]
            if dronecap([*sim, "--seed", "0"], log) != 0:
                return {"case": name, "error": "simulate failed (see log)"}
        sfm_args += ["--gt", str(source / "flight.json")]
    if dronecap(["ingest", str(source), "--workdir", str(d)], log) != 0:
        return {"case": name, "error": "ingest failed (see log)"}
    if "no priors" in name:
        strip_priors(d / "frames.h5")
    t = time.perf_counter()
    code = dronecap(sfm_args, log)
    seconds = time.perf_counter() - t
    report_path = d / "sfm" / "report.json"
    if not report_path.exists():
        return {"case": name, "error": f"sfm exit {code}, no report (see log)"}
    return row_of(name, d, json.loads(report_path.read_text()), seconds)


def row_of(name: str, d: Path, report: dict, seconds: float) -> dict:
    """Table row from a work folder's frames.h5 stage attrs and the sfm report."""
    from dronecap.datasets.format import open_dataset

    ds = open_dataset(d / "frames.h5")
    decoded = ds.attrs.get("decoded")
    acc = report.get("accuracy") or {}
    row = {
        "case": name,
        "frames_in": decoded,
        "kept": report["frames_total"],
        "registered_pct": 100.0 * report["registration_rate"],
        "reproj_px": (report.get("quality") or {}).get("mean_reprojection_error_px"),
        "seconds": seconds,
        "status": report["status"],
        "remedy": report.get("remedy"),
        "camera": (report.get("camera") or {}).get("mode"),
    }
    if "ate_percent" in acc:
        row.update(ate_pct=acc["ate_percent"], rot_deg=acc["rot_median_deg"])
        if "error" not in (report.get("priors") or {"error": 1}):
            row.update(scale_err_pct=100 * abs(acc["scale"] - 1), gravity_deg=acc["gravity_deg"])
    return row


def verdict(row: dict) -> str:
    """'met', 'NOT met (...)' or '' against :data:`FLOORS`."""
    floor = FLOORS.get(row["case"])
    if floor is None:
        return ""
    if "error" in row:
        return "NOT met (failed)"
    reg, ate, rot, scale, grav = floor
    missed = []
    if row["registered_pct"] < reg:
        missed.append(f"registered < {reg:g} %")
    for key, lim, label in (
        ("ate_pct", ate, "ATE"),
        ("rot_deg", rot, "rotation"),
        ("scale_err_pct", scale, "scale"),
        ("gravity_deg", grav, "gravity"),
    ):
        if lim is not None and (row.get(key) is None or row[key] > lim):
            missed.append(f"{label} > {lim:g}")
    return "met" if not missed else "NOT met (" + ", ".join(missed) + ")"


def load_of(row: dict) -> str:
    """The 1-minute load average when the row finished (from its ``uptime`` line)."""
    text = row.get("load", "")
    return text.split("load average:")[-1].split(",")[0].strip() if "average:" in text else text


def fmt(v, spec: str) -> str:
    return "–" if v is None else format(v, spec)


def earlier_table(path: Path) -> tuple[dict[str, str], list[str]]:
    """The rows and the notes below the table of an earlier results file.

    Returns ``({case: its table line}, [lines after the table])``, both empty when ``path``
    does not exist: rows of cases not run now are kept as they were written (with their
    load and any hand-written remark), and so are the notes.
    """
    if not path.exists():
        return {}, []
    lines = path.read_text().splitlines()
    table = [i for i, line in enumerate(lines) if line.startswith("| ")]
    if not table:
        return {}, []
    rows = {line.split("|")[1].strip(): line for line in lines[table[0] + 1 : table[-1] + 1]}
    return rows, lines[table[-1] + 1 :]


def write_results(rows: list[dict], args: argparse.Namespace, load: str) -> None:
    """Markdown table + bar plot of registration.

    A case not in ``rows`` keeps its line from the existing results file, so an ``--only``
    run in a fresh ``--work`` folder updates its rows without dropping the others.
    """
    kept, notes = earlier_table(RESULTS / "real_footage.md")
    ran = {r["case"]: r for r in rows}
    lines = [
        "# Real footage and drone capture folders: default `ingest` + `sfm`",
        "",
        "Command: `OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/real_footage.py"
        + (f" --frames {args.frames}" if args.frames != 240 else "")
        + "`",
        f"Times are single-thread wall clock of `sfm` on a 2-core machine shared with other "
        f"jobs; the load column is the 1-minute load average when each row finished (this "
        f"invocation started at load {load.split('load average:')[-1].split(',')[0].strip()}); "
        "rows of cases not run are kept from the earlier table, with their load.",
        "",
        "| case | frames in / kept | registered | reproj. px | sfm s | ATE % | rot. median ° "
        "| scale err. % | gravity ° | camera | remedy | floor | load |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case in CASES:
        if case not in ran:
            if case in kept:
                lines.append(kept[case])
            continue
        r = ran[case]
        if "error" in r:
            lines.append(f"| {r['case']} | {r['error']} | | | | | | | | | | {verdict(r)} | |")
            continue
        lines.append(
            f"| {r['case']} | {fmt(r['frames_in'], 'd')} / {r['kept']} "
            f"| {r['registered_pct']:.1f} % | {fmt(r['reproj_px'], '.3f')} | {r['seconds']:.0f} "
            f"| {fmt(r.get('ate_pct'), '.2f')} | {fmt(r.get('rot_deg'), '.2f')} "
            f"| {fmt(r.get('scale_err_pct'), '.2f')} | {fmt(r.get('gravity_deg'), '.2f')} "
            f"| {r['camera']} | {r['remedy'] or '–'} | {verdict(r)} | {load_of(r)} |"
        )
    lines += notes
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "real_footage.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    registered = [  # (case, % registered) of every table row, run now or kept
        (cells[1].strip(), float(cells[3].split("%")[0]))
        for cells in (line.split("|") for line in lines if line.startswith("| "))
        if cells[3].strip().endswith("%") and cells[1].strip() != "case"
    ]
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(registered) + 1.2))
    ax.barh([c for c, _ in registered], [pct for _, pct in registered], color="tab:blue")
    for i, (case, _) in enumerate(registered):
        floor = FLOORS.get(case)
        if floor:
            ax.plot([floor[0]] * 2, [i - 0.4, i + 0.4], color="tab:red")
    ax.set_xlabel("frames registered, % of kept (red: floor)")
    ax.set_xlim(0, 100)
    ax.invert_yaxis()
    fig.tight_layout()
    fig.savefig(RESULTS / "real_footage.png", dpi=110)


CASES = [
    "himax test_23",
    "himax test_10",
    "himax test_2",
    "himax test_15",
    "himax test_15 (camera of test_23)",
    "lego orbit video",
    "sim nanocockpit, priors",
    "sim nanocockpit, no priors",
    "sim pulp-dronet, priors",
    "sim pulp-dronet, no priors",
]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/dronecap_real_footage"))
    p.add_argument("--only", nargs="*", help="substrings of the case names to run")
    p.add_argument("--frames", type=int, default=240, help="source frames of simulated flights")
    args = p.parse_args()
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    rows = []
    for name in CASES:
        saved = args.work / (slug(name) + ".row.json")
        if args.only is None or any(s in name for s in args.only):
            if name.startswith("himax") and not HIMAX.exists():
                continue
            if name.startswith("lego") and not LEGO.exists():
                continue
            print(f"--- {name}", flush=True)
            row = run_case(name, args.work, args.frames)
            row["load"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout
            saved.write_text(json.dumps(row))
            print(json.dumps(row), flush=True)
            rows.append(row)
    write_results(rows, args, load)


if __name__ == "__main__":
    main()
