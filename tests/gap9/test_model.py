"""GAP9 cost model: each formula on a hand-counted tiny config, the paper's floors, units."""

from __future__ import annotations

import json

import pytest

from dronecap.gap9 import arch
from dronecap.gap9.model import (
    cost_report,
    federated_payload,
    format_report,
    l1_peak,
    largest_tile_in_l2,
    link_time_s,
    total_memory,
)
from dronecap.gap9.paper import (
    DEPLOYMENT,
    TABLE2,
    beyond_rounding,
    calibrate,
    deployment,
    fit_optimizer_ops,
    paper_sum_per_tile,
    table2,
)
from dronecap.gap9.platform import Platform, parse_bytes, platform_from_dict
from dronecap.nerf.config import preset
from tests.gap9.conftest import TOY


def test_toy_parameter_counts():
    c = arch.counts(TOY, "paper")
    # hash: T rows at each of the 2 levels = 64 rows, x F=2 -> 128 values
    assert (c.hash_rows, c.hash_params) == (64, 128)
    # stored rows: level 0 (res 2) is dense with 3^3 = 27 < 32 rows; level 1 (res 4) 5^3 > 32 -> 32
    assert c.hash_rows_stored == 27 + 32
    assert arch.counts(TOY, "stored").hash_params == 59 * 2
    # density MLP 4 -> 4 -> 3: 16 + 12 = 28; colour MLP (3 geo + 1 SH) -> 4 -> 1: 16 + 4 = 20
    assert (c.density_mlp_params, c.color_mlp_params, c.params) == (28, 20, 176)
    assert c.grid_cells == 64


def test_toy_activation_bytes(gap9):
    n = gap9.numerics
    # forward blobs: enc 4 + hidden 4 + density out 3 + SH 1 + colour in 4 + hidden 4 + out 1 = 21
    assert sum(arch.activation_values(TOY).values()) == 21
    # boundary gradients: enc 4 + density out 3 + colour in 4 + render (C + 1) 2 = 13
    # -> (21 + 13) fp16 + 12 B fp32 position = 80 B
    assert arch.act_bytes_per_sample(TOY, n) == 80
    # every gradient buffer (all blobs but SH): 20 -> (21 + 20) x 2 + 12 = 94 B
    assert arch.tile_bytes_per_sample(TOY, n) == 94


def test_toy_ops_per_sample():
    per = arch.ops_per_sample(TOY)
    # hash: 2 levels x (12 setup + 8 corners x (6 index + 2 weight + 2F blend)) = 2 x 108
    assert per["forward"]["hash"] == per["backward"]["hash"] == 216
    # MLPs: forward 2 ops/MAC, backward 4: density 28 MACs, colour 20 MACs
    assert (per["forward"]["density_mlp"], per["backward"]["density_mlp"]) == (56, 112)
    assert (per["forward"]["color_mlp"], per["backward"]["color_mlp"]) == (40, 80)
    # elementwise forward: ReLU 8 + exp 1 + sigmoid 4 + SH 3 + rendering (6 + 2C) 8 = 24
    # backward: ReLU 8 + exp 1 + sigmoid 2 + rendering 2 x 8 = 27
    assert (per["forward"]["elementwise"], per["backward"]["elementwise"]) == (24, 27)
    # density query: hash 216 + MLP 56 + ReLU 4 + exp 1 + EMA 3
    assert arch.density_query_ops(TOY) == 280


def test_toy_step_ops_and_memory(gap9):
    rep = cost_report(TOY, gap9, samples_per_pixel=2.0)
    ops = rep["ops"]["step"]
    assert ops["forward"] == 8 * 336 and ops["backward"] == 8 * 435
    assert ops["loss"] == pytest.approx(8 / 2 * 6)  # 4 rays x Huber (4 + 2) x 1 channel
    # the fitted 53.9 ops per value (Table II) on all + weight decay on the 48 MLP weights
    assert ops["optimizer"] == pytest.approx(53.9 * 176 + 2 * 48)
    # grid, the trainer's rule: every step before step 32, so 2 warm-up updates x 64 cells +
    # 8 later ones x 32 cells = 384 queries x 280 ops, + 10 updates x 64 cells x 2 ops; over
    # 10 steps
    assert ops["occupancy_amortised"] == pytest.approx((384 * 280 + 10 * 64 * 2) / 10)
    # the paper's fixed rule: 2 warm-up updates, then (10 - 2) // 4 = 2 of 32 cells
    fixed = cost_report(TOY, gap9, samples_per_pixel=2.0, grid_rule="fixed")["ops"]["step"]
    assert fixed["occupancy_amortised"] == pytest.approx((192 * 280 + 4 * 64 * 2) / 10)
    mem = total_memory(TOY, gap9)
    # 176 values x (4 param + 4 grad + 8 moments) = 2816; 8 samples x 80 B; 64 cells x 5 B; 100 px
    assert (mem["parameters"], mem["gradients"], mem["optimizer_state"]) == (704, 704, 1408)
    assert (mem["activations"], mem["occupancy_grid"], mem["images"]) == (640, 320, 100)
    assert mem["total"] == 3876
    # L3 resident with 3 stored images: 2816 + 320 + 300
    assert rep["memory"]["l3"]["total"] == 3436


def test_toy_l3_traffic_and_energy(gap9):
    rep = cost_report(TOY, gap9, samples_per_pixel=2.0)
    tile = rep["l3_traffic"]["tile"]
    # params read fp32 + gradients read and written fp32: 12 B per value
    assert tile["hash_params_and_grads"] == 128 * 12 and tile["mlp_params_and_grads"] == 48 * 12
    # 2 rays per tile test 16 flags each; 2 target pixels of 1 channel
    assert (tile["occupancy_flags"], tile["pixels"]) == (32, 2)
    # Adam reads param, grad (read + zero), 2 moments and writes param + moments: 4+8+8+4+8 = 32
    assert rep["l3_traffic"]["adam_step"] == 176 * 32
    assert rep["l3_traffic"]["step"] == 2 * tile["total"] + 176 * 32
    lat, e = rep["latency"], rep["energy"]
    # occupancy updates: the 128 fp32 hash values (512 B) once per 4-query tile, and every
    # cell's EMA read + written and flag written (64 x 9 B); 2 warm-up updates of 64 queries
    # (16 tiles) and 8 later ones of 32 (8 tiles)
    occupancy = 2 * (16 * 512 + 576) + 8 * (8 * 512 + 576)
    assert rep["l3_traffic"]["occupancy_run"] == occupancy
    run_bytes = 10 * rep["l3_traffic"]["step"] + occupancy
    assert e["soc_run"] == pytest.approx(lat["train"] * 0.060)
    assert e["l3_run"] == pytest.approx(run_bytes * 90e-12)
    assert e["run"] == pytest.approx(e["soc_run"] + e["l3_run"])
    assert e["step"] == pytest.approx(e["run"] / 10)
    # a frame of 10^2 px x 2 spp = 200 samples = 50 forward tiles, each reading 176 fp32 values
    # and its 2 rays' 32 flags
    assert e["frame"] == pytest.approx(lat["render_frame"] * 0.060 + 50 * (176 * 4 + 32) * 90e-12)
    assert set(e["assumptions"]) == {"SoC power", "L3 access energy", "not counted"}
    assert "60 mW" in e["assumptions"]["SoC power"]


def test_l1_and_l2_placement(gap9):
    cfg = preset("tiny-dronerf")
    l1 = l1_peak(cfg, gap9)
    # widest layer 64x64: 4096 x (2 + 4) B weights + grads; 1 KiB per sample double-buffered;
    # (128 KiB - 18 KiB - 24 KiB) / 1 KiB = 86 -> 80 (multiple of 8 cores)
    assert l1["subtile"] == 80 and l1["bytes"] == 24576 + 80 * 1024
    assert "64x64" in l1["layer"]
    assert largest_tile_in_l2(cfg, gap9, 13.0) == 1024
    assert largest_tile_in_l2(cfg.replace(hidden=1024), gap9, 13.0) < 1024


def test_report_is_json_and_readable(gap9):
    rep = cost_report(preset("tiny-dronerf"), gap9)
    back = json.loads(json.dumps(rep))
    assert back["verdicts"]["l2"]["fits"] is True
    text = format_report(rep)
    assert "L2 peak" in text and "DOES NOT FIT" not in text


def test_over_budget_config_reported(gap9):
    # Instant-NGP's row: 2^18 samples untiled and T = 2^19 state (268 MB) cannot fit 32 MiB
    rep = cost_report(preset("instant-ngp"), gap9)
    assert rep["verdicts"]["l3"]["fits"] is False
    assert rep["verdicts"]["untiled_total_in_l3"]["fits"] is False
    assert "DOES NOT FIT" in format_report(rep)
    # a 1024-wide MLP overflows L2 with 1024-sample tiles
    assert cost_report(preset("tiny-dronerf").replace(hidden=1024), gap9)["verdicts"]["l2"][
        "fits"
    ] is False  # fmt: skip


@pytest.mark.parametrize("name", list(TABLE2))
def test_table2_row_within_3_percent(name, gap9):
    row = next(r for r in table2(gap9) if r["name"] == name)
    assert abs(row["mem_err_rounding"]) <= 0.03, row
    assert abs(row["mem_err"]) <= 0.04, row
    assert abs(row["gop_err"]) <= 0.03, row


def test_beyond_rounding():
    assert beyond_rounding(21.4, 21) == 0.0  # inside [20.5, 21.5]
    assert beyond_rounding(22.2, 23) == pytest.approx(-0.3 / 23)
    assert beyond_rounding(542.8, 527) == pytest.approx(15.3 / 527)


def test_shipped_optimizer_ops_is_the_table2_fit(gap9):
    fit = fit_optimizer_ops(gap9)
    assert gap9.calibration.optimizer_ops_per_value == pytest.approx(fit, rel=0.01)
    # more than Adam's own arithmetic; Adam on GAP9 stays bound by its L3 traffic
    assert fit > arch.ADAM_OPS
    assert cost_report(preset("tiny-dronerf"), gap9)["latency"]["adam_bound"] == "L3 DMA"


def test_deployment_latencies_within_10_percent(gap9):
    rows = deployment(gap9)
    assert {r["name"] for r in rows} == set(DEPLOYMENT)
    for r in rows:
        if r["reproducible"]:
            assert abs(r["err"]) <= 0.10, r
    # the paper's 73 ms is the sum of every figure once per tile (docs/gap9.md); our consistent
    # amortisation is far below it and says so rather than bending
    assert paper_sum_per_tile() == pytest.approx(0.073)
    amort = next(r for r in rows if r["name"] == "per_tile_amortised")
    assert not amort["reproducible"] and amort["model"] < 0.05


def test_shipped_calibration_is_the_fit(gap9):
    fit = calibrate(gap9)
    cal = gap9.calibration
    assert cal.mlp_fwd_ops_per_cycle == pytest.approx(fit.mlp_fwd_ops_per_cycle, rel=0.01)
    assert cal.mlp_bwd_ops_per_cycle == pytest.approx(fit.mlp_bwd_ops_per_cycle, rel=0.01)
    assert cal.hash_cycles_per_corner == pytest.approx(fit.hash_cycles_per_corner, rel=0.01)
    # effective MLP throughput is a fraction of the fp16 peak (4 FPUs x 2 lanes x FMA = 16)
    assert 0 < cal.mlp_fwd_ops_per_cycle < gap9.peak_ops_per_cycle()


def test_yaml_matches_dataclass_defaults(gap9):
    assert gap9 == Platform()


def test_federated_payload_and_link(gap9):
    cfg = preset("tiny-dronerf")
    # 16 levels x 8192 rows x 2 features + 9408 MLP weights, fp16
    assert federated_payload(cfg, False) == (262144 + 9408) * 2
    assert federated_payload(cfg, True) == (262144 + 9408 + 128**3) * 2
    assert federated_payload(cfg, False, bytes_per_value=4) == (262144 + 9408) * 4
    # 15 Mbit/s: 1.875e6 bytes per second
    assert link_time_s(1_875_000, gap9) == pytest.approx(1.0)
    # the paper's 2.24 s: 4 drones x (up + down) x 2^18 fp16 values in turn
    assert link_time_s(8 * 524288, gap9) == pytest.approx(2.237, abs=1e-3)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("32MB", 32_000_000),
        ("1.5MB", 1_500_000),
        ("128kB", 128_000),
        ("128KiB", 131_072),
        ("1.5MiB", 1_572_864),
        ("4096", 4096),
        (" 2 GB ", 2_000_000_000),
        ("512b", 512),
        (300, 300),
    ],
)
def test_parse_bytes(text, expected):
    assert parse_bytes(text) == expected


@pytest.mark.parametrize("bad", ["32XB", "MB", "-1MB", "15Mbit", "1.2.3kB", ""])
def test_parse_bytes_refuses(bad):
    with pytest.raises(ValueError):
        parse_bytes(bad)


def test_platform_from_dict():
    p = platform_from_dict({"l2_bytes": "2MB", "numerics": {"act_bytes": 4}})
    assert p.l2_bytes == 2_000_000 and p.numerics.act_bytes == 4
    assert p.numerics.param_bytes == 4  # untouched fields keep the defaults
    with pytest.raises(ValueError, match="unknown platform fields: l4_bytes"):
        platform_from_dict({"l4_bytes": 1})
    with pytest.raises(ValueError, match="hash_rows"):
        platform_from_dict({"hash_rows": "dense"})
    # fp32 activations double the per-sample activation bytes (minus the fp32 position)
    assert arch.act_bytes_per_sample(TOY, p.numerics) == 34 * 4 + 12


def test_sized_preset_fits_where_tiny_dronerf_fits(gap9):
    """tiny-dronerf-sized changes only sizing (finest level, sample spacing, grid): the same
    table and MLPs, no more modelled GAP9 memory or work per step, and it still fits."""
    tiny, sized = preset("tiny-dronerf"), preset("tiny-dronerf-sized")
    a, b = cost_report(tiny, gap9), cost_report(sized, gap9)
    assert (sized.log2_hashmap, sized.levels, sized.features, sized.hidden) == (
        tiny.log2_hashmap,
        tiny.levels,
        tiny.features,
        tiny.hidden,
    )
    assert b["memory"]["untiled"]["total"] < a["memory"]["untiled"]["total"]
    assert b["ops"]["step"]["total"] <= a["ops"]["step"]["total"]
    assert all(v["fits"] for v in b["verdicts"].values())


def test_a_run_is_costed_in_gap9_tiles():
    """A CPU run that accumulated one 8192-sample tile is deployed on GAP9 in 1024-sample tiles
    (the same model and batch): the L2 check is about the deployed tile."""
    from dronecap.gap9.model import DEPLOY_TILE, cost_report, deployed
    from dronecap.nerf.config import preset

    cpu = preset("tiny-dronerf").replace(tile_samples=8192, log2_hashmap=14, n_max=320)
    assert not cost_report(cpu)["verdicts"]["l2"]["fits"]
    dep = deployed(cpu)
    assert dep.tile_samples == DEPLOY_TILE and dep.batch_samples == cpu.batch_samples
    assert cost_report(dep)["verdicts"]["l2"]["fits"]
    assert deployed(preset("tiny-dronerf").replace(tile_samples=512)).tile_samples == 512
