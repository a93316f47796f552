"""dronecap.camera: the one camera type (intrinsics + lens distortion) every stage uses.

:class:`Camera` holds fx, fy, cx, cy in pixels of the stored image and a distortion model;
OpenCV does the projection and undistortion maths.
"""

from dronecap.camera.model import DISTORTION_PARAMS, Camera

__all__ = ["DISTORTION_PARAMS", "Camera"]
