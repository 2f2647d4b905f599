"""What the session-wide pipeline runs of tests/conftest.py are made with, for the tests that read them or make
runs of their own to compare with them. A test helper, not shipped."""

from __future__ import annotations

BUILDING_SPACE = "clip-vit-b32"  # the building's label-set space needs no text encoder
# ``panogs run`` arguments of the building's tiled run: two tiles, no appearance fit (no label reads it).
BUILDING_TILED_ARGV = ("--tiles", "2x1", "-q", "--set", "appearance.enabled=false")
# The building's untiled run: the appearance fit off, as in the tiled one.
BUILDING_NO_FIT = {"appearance": {"enabled": False}}
