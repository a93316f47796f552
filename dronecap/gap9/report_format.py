"""Readable text of a GAP9 cost report (the dict of :func:`dronecap.gap9.model.cost_report`)."""

from __future__ import annotations

from dronecap.gap9.platform import format_bytes


def _s(t: float) -> str:
    if t >= 3600:
        return f"{t / 3600:.2f} h"
    if t >= 60:
        return f"{t / 60:.1f} min"
    return f"{t:.3g} s" if t >= 1 else f"{t * 1e3:.3g} ms"


def _j(joules: float) -> str:
    return f"{joules:.3g} J" if joules >= 1 else f"{joules * 1e3:.3g} mJ"


def _config_rows(r: dict) -> list[tuple[str, str]]:
    """The report's configuration rows: batch and table, images, parameters."""
    cfg, counts = r["config"], r["counts"]
    rows = [
        ("B / tile / log2 T / L x F",
         f"{cfg['batch_samples']} / {cfg['tile_samples']} / {cfg['log2_hashmap']} / "
         f"{cfg['levels']} x {cfg['features']}"),
        ("images/step, resolution", f"{cfg['images_per_step']}, {cfg['resolution']} px"),
    ]  # fmt: skip
    far = counts.get("far_field_params", 0)
    params = f"{counts['hash_params']} + {counts['mlp_params']}"
    if far:  # a far field (nerf.far_field): its kind and values
        label = f"params (hash + MLP + far field {cfg.get('far_field')})"
        return [*rows, (label, f"{params} + {far}")]
    return [*rows, ("params (hash + MLP)", params)]


def format_report(report: dict) -> str:
    """A readable multi-section table of a :func:`cost_report` dict."""
    r, cfg, mem, lat = report, report["config"], report["memory"], report["latency"]
    rows: list[tuple[str, str]] = []

    def section(title: str) -> None:
        rows.append((f"-- {title}", ""))

    section(f"configuration on {r['platform']}")
    rows.extend(_config_rows(r))
    section("memory (untiled, Table II accounting)")
    for k, v in mem["untiled"].items():
        rows.append((k, format_bytes(v)))
    section("placement (tiled GAP9)")
    l1 = mem["l1_peak"]
    rows.append(
        ("L1 peak", f"{format_bytes(l1['bytes'])} ({l1['layer']}, sub-tile {l1['subtile']})")
    )
    rows.append(("L2 peak", f"{format_bytes(mem['l2_peak']['bytes'])} ({mem['l2_peak']['phase']})"))
    rows.append(("L3 resident", format_bytes(mem["l3"]["total"])))
    rows.append(("largest tile in L2", str(mem["largest_tile_in_l2"])))
    section("operations")
    rows.append(("trained / marched samples", f"{r['assumptions']['trained_fraction']:.2f}"))
    for k, v in r["ops"]["step"].items():
        rows.append((f"{k} / step", f"{v / 1e9:.3f} GOp"))
    rows.append(("per rendered frame", f"{r['ops']['frame'] / 1e9:.2f} GOp"))
    section("latency")
    for pas in ("forward", "backward"):
        parts = ", ".join(f"{k} {v * 1e3:.2f}" for k, v in lat["kernels_per_tile"][pas].items())
        rows.append((f"{pas} / tile", f"{_s(lat[pas + '_tile'])} ({parts} ms)"))
    rows.append(
        (
            "L3 DMA / tile",
            f"{_s(lat['l3_dma_tile'])} ({'hidden' if lat['dma_hidden'] else 'exposed'})",
        )
    )
    rows.append(("Adam / step", f"{_s(lat['adam_step'])} ({lat['adam_bound']} bound)"))
    rows.append(("occupancy update", _s(lat["occupancy_update"])))
    a = r["assumptions"]
    rows.append((
        "occupancy updates of the run",
        f"{a['grid_updates']['warmup']} warm-up + {a['grid_updates']['steady']} later "
        f"({a['grid_rule']} rule, hull {a['hull_fraction']:.0%} of the cells): "
        f"{_s(lat['occupancy_run'])}",
    ))  # fmt: skip
    rows.append(
        ("step / amortised per tile", f"{_s(lat['step'])} / {_s(lat['per_tile_amortised'])}")
    )
    rows.append((f"training ({cfg['steps']} steps)", _s(lat["train"])))
    rows.append(("render one frame", f"{_s(lat['render_frame'])} ({lat['render_tiles']} tiles)"))
    section("L3 traffic")
    rows.append(("per tile", format_bytes(r["l3_traffic"]["tile"]["total"])))
    rows.append(("per step (incl. Adam)", format_bytes(r["l3_traffic"]["step"])))
    e = r["energy"]
    section("energy: SoC power x time + L3 bytes x J/B")
    rows.append(("step", f"{_j(e['step'])} (SoC {_j(e['soc_step'])} + L3 {_j(e['l3_step'])})"))
    l3_share = e["l3_run"] / e["run"] if e["run"] > 0 else 0.0  # a 0-step run spends nothing
    rows.append((f"run ({cfg['steps']} steps)", f"{_j(e['run'])} (L3 {l3_share:.0%})"))
    rows.append(("render one frame", _j(e["frame"])))
    rows.extend(e["assumptions"].items())
    section(f"federated round ({r['link']['clients']} drones, up + down)")
    for g in ("no_grid", "grid"):
        rows.append((
            f"payload {g.replace('_', ' ')}",
            f"{format_bytes(r['link']['payload_' + g])} -> {_s(r['link']['round_s_' + g])}",
        ))  # fmt: skip
    section("verdicts")
    for k, v in r["verdicts"].items():
        ok = "fits" if v["fits"] else "DOES NOT FIT"
        rows.append((k, f"{ok}: {format_bytes(v['need'])} of {format_bytes(v['have'])}"))
    width = max(len(a) for a, _ in rows if not a.startswith("--"))
    return "\n".join(a if a.startswith("--") else f"  {a:<{width}}  {b}" for a, b in rows)
