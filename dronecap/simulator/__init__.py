"""dronecap.simulator: synthetic nano-drone captures with exact ground truth.

:func:`simulate` renders a flight (corridor or orbit scene, open3d ray casting) through a lens,
a sensor and a Wi-Fi link (:mod:`~dronecap.simulator.sensor`, :mod:`~dronecap.simulator.stream`)
to a video or a drone capture folder with onboard telemetry (:mod:`~dronecap.simulator.formats`,
:mod:`~dronecap.simulator.telemetry`), plus a ground-truth ``flight.json``;
:func:`render_flight` returns the delivered frames in memory. Heavy libraries (open3d, OpenCV,
scipy) are imported inside the functions that use them.
"""

from dronecap.simulator.simulate import Capture, capture_preset, render_flight, simulate

__all__ = ["Capture", "capture_preset", "render_flight", "simulate"]
