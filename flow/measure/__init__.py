"""The measurement, shared by every method: from a method's flow fields to the displacement a
run reports (paper sections 3.1, 3.5-3.7).

``poi`` turns masks into POIs and region labels; ``reference`` checks the reference frame;
``driver`` runs the frame loops (dense: every frame against the reference; sparse: frame to
frame) with ``background`` removing the camera's motion and ``photometric`` giving each
frame's residual and uncertainty; ``tracks`` and ``storage`` hold the per-POI tracks (on disk
for long clips); ``quality`` flags frames and ``filtering`` applies eq. 10-12 and averages
(``robust``: their shared constants); ``formats`` writes and merges raw-tracks parts. This
file imports nothing.
"""
