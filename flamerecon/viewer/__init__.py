"""The web viewer (``flamerecon view RUN_DIR``, ``fr.view(rec)``): a viser server above the run
layer, since it keeps serving. :mod:`.content` gathers what it shows, :mod:`.server` serves it,
:mod:`.command` is the command line."""
