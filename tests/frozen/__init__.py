"""Frozen reference numbers (issue 10, item 1: "safety net first").

``make_frozen.py`` computed ``data/*.json`` with the reference code (commit recorded in each file); the
``test_frozen_*`` modules recompute on the same seeded scenes and compare with tight tolerances. All access to
result objects goes through :mod:`.adapters` (one small function per quantity): after a refactor, re-point those,
never the JSON. Regenerate only on purpose (a deliberate change of numbers), and say why in the commit.
"""
