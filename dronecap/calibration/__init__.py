"""dronecap.calibration: the ``dronecap calibrate`` stage (board views -> a Camera).

:mod:`.targets` (boards and their detection), :mod:`.calibrate` (OpenCV calibration, rejected
views, warnings), :mod:`.views` (images, picking views from a video through
:mod:`dronecap.capture`), :mod:`.plot` (the corners/errors picture). It writes its result with
:func:`dronecap.camera.files.write_calibration`; it may use ``camera`` and ``capture``.
"""
