"""``python -m torchsurf``: the ``torchsurf`` command (:mod:`torchsurf.cli`)."""

from .cli import entry_point

entry_point()
