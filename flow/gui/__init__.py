"""``refflow gui``: a page in the browser to pick the ROI, draw the mask, click the scale, run
``refflow track`` and look at the result.

``command`` adds the subcommand to the CLI and runs it; the server (:mod:`flow.gui.server`,
standard library only) listens on 127.0.0.1, serves the page's files shipped in
``flow/gui/static`` (plain HTML, JavaScript and canvas: nothing is downloaded) and writes only
into one output folder (:mod:`flow.gui.paths`). What the user chose is saved as a project
JSON (:mod:`flow.gui.project`), which ``refflow track --project FILE`` repeats. This file
imports nothing.
"""
