"""dronecap.camera: the one camera type (intrinsics + lens distortion) and its files.

- :class:`Camera` holds fx, fy, cx, cy in pixels of the stored image and a distortion model;
  OpenCV does the projection and undistortion maths (``camera/model.py``).
- :func:`load_camera` reads every form of known intrinsics (``fx,fy,cx,cy``, the calibration
  JSON, the simulator's flight.json, OpenCV YAML/XML) into a Camera sized to the frames
  (``camera/files.py``), which also writes the calibration JSON/YAML.

The calibration stage that finds a Camera from board views is :mod:`dronecap.calibration`; this
package imports no other stage (every stage uses it).
"""

from dronecap.camera.files import load_camera
from dronecap.camera.model import DISTORTION_PARAMS, Camera

__all__ = ["DISTORTION_PARAMS", "Camera", "load_camera"]
