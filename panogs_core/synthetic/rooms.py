"""Which room a preset gets: a zoned room (``layout.py``) or, for a realistic spec, a studio (``scan_layout.py``).

Apart from both so that ``scan_layout.py`` can build on ``layout.py``'s helpers without the two importing each
other.
"""

from __future__ import annotations

import numpy as np

from panogs_core.synthetic.layout import Layout, build_zoned_layout
from panogs_core.synthetic.presets import SyntheticSpec
from panogs_core.synthetic.scan_layout import build_scan_layout


def build_layout(spec: SyntheticSpec, rng: np.random.Generator) -> Layout:
    """Draw a furnished room.

    Args:
        spec: Room size ranges and zone length; a realistic spec gets a studio (``scan_layout.py``).
        rng: Source of every random choice (the layout is a pure function of its state).

    Returns:
        The room as boxes with instance and class ids, colours and contacts.
    """
    if spec.realistic:
        return build_scan_layout(spec, rng)
    return build_zoned_layout(spec, rng)
