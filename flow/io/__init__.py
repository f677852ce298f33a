"""Reading what a user hands the tool: the frames of a video, an image folder or a high-speed
camera recording, and the JSON files (scale, calibration, video origin).

``source`` opens any of them as one :class:`~flow.io.source.FrameSource` that streams grey
frames with their times (never the whole clip); ``camfiles`` reads Photron and Phantom
recordings, ``imagefiles`` checks and reads image files, ``jsonfiles`` the JSON inputs, and
``errors`` holds the one error every reader raises for bad input. This file imports nothing.
"""
