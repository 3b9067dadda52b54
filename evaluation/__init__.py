"""Accuracy of a release against the simulator's ground truth: not a stage, it reads a published release.

:mod:`evaluation.release` measures every published action (``ultrastage evaluate``, and ``ultrastage run`` after
publishing); :mod:`evaluation.heldout` is the paper's held-out view protocol (table 1) it uses.
"""
