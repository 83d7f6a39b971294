"""Capture: devices, sync, live sessions, recordings.

- ``frame``, ``camera``, ``errors``: the ``Frame`` record, the ``Camera`` protocol and
  settings, the ``CaptureError`` family (docs/conventions.md [errors]).
- ``v4l2`` (linuxpy: kernel timestamps and sequence numbers), ``opencv_camera`` (CAP_V4L2
  fallback), ``discovery`` (sysfs: /dev/videoN -> USB VID:PID, serial, port; pyusb reset).
- ``sync_protocol`` (docs/sync-protocol.md), ``clock_model`` (device -> host clock fit),
  ``syncbox`` (host driver over pyserial).
- ``session`` (cameras + sync box -> frame sets), ``recording`` / ``replay`` (crash-safe
  session folders; ``replay.recording_frames`` for offline reprocessing), ``live`` (the call
  behind ``mocap capture``), ``detections`` (2D detections table).

Submodules are imported on use; this package imports nothing heavy.
"""
