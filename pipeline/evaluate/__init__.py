"""Held-out evaluation: image metrics (``metrics``), per-sequence scoring of every normal-map
method against the reference surface (``sequence``) and the Markdown report (``report``)."""
