"""Reading what a user hands the tool: the frames of a video, an image folder, a TIFF stack or
a high-speed camera recording, and the JSON files (scale, calibration, video origin).

``source.open_source`` is the one opener: it picks the reader for a path, one per kind of
input (``video``, ``folder``, ``tiffstack``, ``camera``), each a ``frames.FrameSource`` that
streams grey frames with their times (never the whole clip); the folder and the stack share
``frames.ImageSequence``. ``camera`` reads a recording through its
format's reader (``photron``, ``phantom``; what they share: ``camfiles``). ``imagefiles``
checks and reads image files, ``jsonfiles`` the JSON inputs, and ``errors`` holds the one
error every reader raises for bad input. This file imports nothing.
"""
