"""The whole displacement field (``refflow track --field``, ``refflow field-plot``).

* :mod:`flow.field.stream`: every mask pixel's displacement in every frame, streamed frame by
  frame into an HDF5 file beside the run's CSV; its reader and the merge of parts.
* :mod:`flow.field.plot`: maps, a movie and operational deflection shapes drawn from that file.
"""
