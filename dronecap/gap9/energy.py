"""Energy of a configuration on the platform: the SoC's power over the modelled time, plus the
off-chip L3 accesses at a per-byte energy.

Both figures come from the platform file with their sources (``power_source``,
``l3_energy_source`` in ``gap9.yaml``); the report carries them and the assumptions beside the
joules, so a reader sees what the numbers rest on. The SoC power is the paper's average at the
modelled clock (it includes the L2/L1 DMA and the cluster); the L3 PSRAM is a separate chip on
the shield, so its access energy is added on top.
"""

from __future__ import annotations

from dronecap.gap9.platform import Platform


def assumptions(p: Platform) -> dict[str, str]:
    """What every energy figure rests on, by name, in the words the report prints."""
    return {
        "SoC power": f"{p.power_w * 1e3:.0f} mW at {p.clock_hz / 1e6:.0f} MHz while training "
        f"({p.power_source})",
        "L3 access energy": f"{p.l3_joules_per_byte * 1e12:.0f} pJ/B read or written "
        f"({p.l3_energy_source})",
        "not counted": "radio, camera and flight; idle time between steps",
    }


def energy_report(lat: dict, traffic: dict, steps: int, p: Platform) -> dict:
    """Joules per optimizer step, per run of ``steps`` steps and per rendered frame.

    Args:
        lat: :func:`dronecap.gap9.timing.latency` (seconds: ``step``, ``train``, ``render_frame``).
        traffic: :func:`dronecap.gap9.timing.l3_traffic` (bytes: ``step``, ``occupancy_run``,
            ``render_frame``).
        steps: optimizer steps of the run.
        p: the platform (power, L3 energy per byte, their sources).
    Returns:
        {"power_w", "power_source", "l3_joules_per_byte", "l3_energy_source", "assumptions",
        "soc_step", "l3_step", "step", "soc_run", "l3_run", "run", "frame"}; joules. The
        occupancy updates' time and L3 bytes are amortised into the step figures.
    """
    run_bytes = steps * traffic["step"] + traffic["occupancy_run"]
    soc_run = lat["train"] * p.power_w
    l3_run = run_bytes * p.l3_joules_per_byte
    per_step = max(steps, 1)
    return {
        "power_w": p.power_w,
        "power_source": p.power_source,
        "l3_joules_per_byte": p.l3_joules_per_byte,
        "l3_energy_source": p.l3_energy_source,
        "assumptions": assumptions(p),
        "soc_step": soc_run / per_step,
        "l3_step": l3_run / per_step,
        "step": (soc_run + l3_run) / per_step,
        "soc_run": soc_run,
        "l3_run": l3_run,
        "run": soc_run + l3_run,
        "frame": lat["render_frame"] * p.power_w + traffic["render_frame"] * p.l3_joules_per_byte,
    }
