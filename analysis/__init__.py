"""Evaluation of tracked displacement against the simulated ground truth.

Reads files only (``docs/formats.md``); never imports ``sim`` or ``flow``.

* ``sync``: 30 Hz zero-phase Butterworth on the 1 kHz reference, sub-sample
  clock offset by cross-correlation, reference resampled at frame times.
* ``metrics``: RMSE (mm, px), maxima, bias, drift, spectral peaks with
  aliases, occlusion and recovery metrics; keys carry their units.
* ``spectra``: Welch PSD, peak picking, alias prediction.
* ``modal``: multi-point modal identification (FDD + SSI-cov, shared with the
  tool in ``refflow.modal``) vs the model.
* ``figures``, ``report``, ``table1``: Fig. 6-10, summary tables, Table 1.

Command line: ``python -m analysis {evaluate,summary,table1,figures,modal} --help``.
"""
