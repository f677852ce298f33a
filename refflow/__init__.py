"""Neutral infrastructure shared by ``sim``, ``flow`` and ``analysis``.

File plumbing (atomic writes, JSON sidecars, config hashing, package versions), the one
config loader (``refflow.config``), the track CSV format that ``flow`` writes and ``flow`` and
``analysis`` read (``refflow.trackcsv``), spectral peak picking (``refflow.spectra``), the
POIs-vs-corners figure (``refflow.figures``, paper Fig. 6) and output-only modal
identification (``refflow.modal``: from a response alone, no model): nothing that could let
the measurement see the ground truth. It imports none of the three.
"""
