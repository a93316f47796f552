"""dronecap.simulator: synthetic nano-drone flights with exact ground truth.

:func:`simulate` renders a flight (corridor or orbit scene, open3d ray casting) to a video plus
a ground-truth JSON (poses, intrinsics); :func:`render_flight` returns the frames in memory.
Heavy libraries (open3d, OpenCV) are imported inside the functions that use them.
"""

from dronecap.simulator.simulate import render_flight, simulate

__all__ = ["render_flight", "simulate"]
