"""Where a warning should point: the first frame outside torchsurf, torch and the standard
library's ``copy`` and ``pickle`` (through which ``copy.deepcopy(surface)`` reaches torchsurf)."""

from __future__ import annotations

import copy
import copyreg
import os
import pickle
import sys

import torch

_INTERNAL = (*(os.path.dirname(module.__file__) + os.sep
                for module in (sys.modules[__package__], torch)),
             *(module.__file__ for module in (copy, copyreg, pickle)))


def caller_stacklevel() -> int:
    """The ``stacklevel`` for ``warnings.warn`` called by this function's caller that names the
    user's line: the first frame outside torchsurf, torch (``nn.Module.__call__``) and
    ``copy``/``pickle``, however
    deep the library's own calls are (a batch integrated one entry at a time re-enters
    ``forward``). Under ``torch.compile`` (which cannot trace frames) the caller's caller."""
    if torch.compiler.is_compiling():
        return 2
    frame, level = sys._getframe(1), 1
    while frame.f_back is not None and frame.f_code.co_filename.startswith(_INTERNAL):
        frame, level = frame.f_back, level + 1
    return level
